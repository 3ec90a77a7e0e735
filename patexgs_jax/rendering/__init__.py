"""The renderer's stages, one a module; the pipeline that calls them is :mod:`patexgs_jax.render`
(which also fixes the conventions they follow).

  :mod:`.config`: :class:`RenderConfig`, :class:`Capacity`, :class:`RenderOutput` and the constants.
  :mod:`.projection`: per-splat quantities and screen-space bounds, packed into one array.
  :mod:`.binning`: depth-ordered per-tile lists.
  :mod:`.tiling`: how many tiles the compositor advances at once, chosen per device.
  :mod:`.chunks`, :mod:`.kernel`, :mod:`.texture_lookup`, :mod:`.composite`: the compositor (tile
  batches and chunk slots, the pair kernel G, the mip footprint and atlas lookups, front-to-back
  compositing with its hand-written backward); :mod:`.pallas_composite` and :mod:`.pallas_texture`:
  the same compositor as one Pallas GPU kernel (``RenderConfig(compositor="pallas")``).
  :mod:`.gaussian3d`: the projection of 3D Gaussians (3DGS, Mip-Splatting); :mod:`.billboard`:
  BBSplat's square kernel.
"""
