"""MovieWriter: frames streamed to a video file as they come, so memory stays flat however long the run.

MP4 (H.264, yuv420p) through the ffmpeg binary that ``imageio-ffmpeg``
ships: each frame goes down ffmpeg's stdin and is not kept. Without a
working ffmpeg the movie is a GIF (Pillow), which needs every frame at the
end: those are kept at half size (a quarter of the memory) and the GIF runs
at that size. Frame sides must be multiples of 16 (H.264 encoders pad
otherwise); the file is written beside the target and renamed when closed.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mabdi.errors import MabdiError


class MovieError(MabdiError):
    """A movie that cannot be written (bad frame size, encoder failure); the message names the file."""


def ffmpeg_executable() -> str | None:
    """Path of the ffmpeg binary from imageio-ffmpeg (or $IMAGEIO_FFMPEG_EXE), None if there is none."""
    try:
        import imageio_ffmpeg

        return imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError):
        return None


class MovieWriter:
    """Write (H, W, 3) uint8 frames to ``path`` (.mp4, or .gif); use as a context manager.

    ``size`` = (width, height), both multiples of 16. With ``path`` ending in .mp4 and no
    ffmpeg, the movie goes to the same name with .gif (``self.path`` says where).
    """

    def __init__(self, path, size: tuple[int, int], fps: float = 5.0) -> None:
        width, height = size
        if width % 16 or height % 16 or width <= 0 or height <= 0:
            raise MovieError(f"movie {path}: frame size {width}x{height} must be positive multiples of 16")
        self.size = (int(width), int(height))
        self.fps = float(fps)
        self.frames = 0
        path = Path(path)
        if not path.parent.is_dir():
            raise MovieError(f"movie {path}: folder {path.parent} does not exist")
        self._ffmpeg = ffmpeg_executable() if path.suffix.lower() == ".mp4" else None
        self.path = path if self._ffmpeg or path.suffix.lower() == ".gif" else path.with_suffix(".gif")
        self._temporary = self.path.with_name(f".{self.path.stem}.tmp{self.path.suffix}")
        self._gif_frames: list[np.ndarray] = []
        self._writer = None
        if self._ffmpeg:
            os.environ.setdefault("IMAGEIO_FFMPEG_EXE", self._ffmpeg)
            import imageio_ffmpeg

            self._writer = imageio_ffmpeg.write_frames(
                str(self._temporary),
                self.size,
                fps=self.fps,
                codec="libx264",
                pix_fmt_out="yuv420p",
                macro_block_size=16,
                quality=7,
                ffmpeg_log_level="error",
            )
            self._writer.send(None)  # start ffmpeg

    @property
    def encoder(self) -> str:
        return "ffmpeg (H.264)" if self._ffmpeg else "Pillow (GIF)"

    def write(self, frame: np.ndarray) -> None:
        """Append one (height, width, 3) uint8 frame."""
        frame = np.asarray(frame)
        width, height = self.size
        if frame.shape != (height, width, 3) or frame.dtype != np.uint8:
            raise MovieError(f"movie {self.path}: frame must be ({height}, {width}, 3) uint8, got {frame.shape} {frame.dtype}")
        if self._writer is not None:
            try:
                self._writer.send(np.ascontiguousarray(frame))
            except (OSError, RuntimeError) as error:
                raise MovieError(f"movie {self.path}: ffmpeg failed: {error}") from error
        else:
            self._gif_frames.append(frame[::2, ::2].copy())
        self.frames += 1

    def close(self) -> Path:
        """Finish the file and move it into place; returns its path."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        elif self._gif_frames:
            from PIL import Image

            images = [Image.fromarray(f) for f in self._gif_frames]
            images[0].save(self._temporary, format="GIF", save_all=True, append_images=images[1:], duration=int(1000 / self.fps), loop=0)
            self._gif_frames.clear()
        if self._temporary.exists():
            os.replace(self._temporary, self.path)
        return self.path

    def abort(self) -> None:
        """Stop without a file (the temporary one is removed)."""
        if self._writer is not None:
            try:
                self._writer.close()
            except Exception:  # noqa: BLE001 - already failing; the temporary file goes either way
                pass
            self._writer = None
        self._gif_frames.clear()
        if self._temporary.exists():
            self._temporary.unlink()

    def __enter__(self) -> MovieWriter:
        return self

    def __exit__(self, kind, value, traceback) -> None:
        if kind is None:
            self.close()
        else:
            self.abort()


def read_movie_frames(path) -> tuple[int, tuple[int, int]]:
    """(number of frames, (width, height)) of a movie file, read back with ffmpeg (for tests and checks)."""
    path = Path(path)
    if path.suffix.lower() == ".gif":
        from PIL import Image

        with Image.open(path) as image:
            return image.n_frames, image.size
    import imageio_ffmpeg

    reader = imageio_ffmpeg.read_frames(str(path))
    meta = reader.__next__()
    count = sum(1 for _ in reader)
    return count, tuple(meta["size"])
