"""Drawing depth images of meshes: the off-screen renderer and the simulated camera (:mod:`.depth_image`),
a LiDAR's range images as four perspective renders (:mod:`.range_rendering`). The simulator's sensor and
the loop's expected image E draw through them."""
