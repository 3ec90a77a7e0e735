"""The browser viewer: ``python -m patexgs_jax.viewer PATH`` (docs/viewer.md).

  :mod:`.frames`: what a frame is: runs and checkpoints loaded, the browser's camera, one frame of
  each view mode (RGB, depth, normals, alpha, mip level, texture side) rendered at a padded size.
  :mod:`.server`: the viser web server that serves them, its controls and its command line.
"""
