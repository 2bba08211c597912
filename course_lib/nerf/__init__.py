"""NeRF, one module per component (notebooks 06-09).

* :mod:`course_lib.nerf.rays` - one ray per pixel, stratified samples, query points (06).
* :mod:`course_lib.nerf.encoding` - positional encoding (06).
* :mod:`course_lib.nerf.model` - the paper's MLP (07).
* :mod:`course_lib.nerf.render` - volume rendering, hierarchical sampling, chunked image rendering (08).
* :mod:`course_lib.nerf.grid` - the voxel-grid field of the ``fast`` preset (09).
* :mod:`course_lib.nerf.presets` - :class:`TrainConfig` and the presets ``paper`` and ``fast``.
* :mod:`course_lib.nerf.device` - where it runs: ``pick_device()`` (CUDA, then MPS, then the CPU), render chunks.
* :mod:`course_lib.nerf.scene` - the scene's bounds (``SceneBounds``) and the training rays (uint8 pixels).
* :mod:`course_lib.nerf.schedule` - the grid's training schedule, as callbacks the field supplies.
* :mod:`course_lib.nerf.inference` - forward-only rendering: evaluation, snapshots, novel views (08-09).
* :mod:`course_lib.nerf.checkpoint` - checkpoints, written during training, read on any device.
* :mod:`course_lib.nerf.train` - the training loop (08).
* :mod:`course_lib.nerf.run` - around the loop: the run's clock, its outputs (snapshots, checkpoints, evaluations), the progress bar.
* :mod:`course_lib.nerf.cli_nerf` - ``python -m course_lib nerf train|eval|render`` (options made from :class:`TrainConfig`).
"""
