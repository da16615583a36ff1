"""The stages of the frame path (docs/architecture.md): registration to the map (with its anchor and its
checks of a run's poses), the expected image E, the classifier, refinement, object removal (its rules and
the stage) and the world mesh the surface's triangles are appended to. Each is called by the loop with the
frame's values (:mod:`mabdi.frame_values`) and is a VTK filter of the pipeline API too."""
