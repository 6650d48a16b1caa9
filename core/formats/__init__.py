"""File and folder formats every layer reads and writes: images and EXR maps, the 3DGS PLY,
the scene folder (:mod:`.scene_dir`) and the run folder (:mod:`.run_dir`)."""
