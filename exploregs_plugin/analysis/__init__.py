"""Blur-Trap diagnostics: gradient branches and their directions, alpha-blending attenuation,
the ablation experiment specs, and the figures (``eg-analyze``).

Modules: ``branches`` (per-path gradients of the means), ``directions`` (cosines with the ray
and the optical axis), ``blending`` (per-pixel and per-depth-rank transmittance and screen-space
gradient), ``plots`` (figures and tables), ``sampling`` (views and iterations), ``probing`` (a short run that stops to probe),
``tensorboard`` (the training-time logger), ``experiments`` (ablation specs for eg-bench).
The degraded depth maps of the depth-supervision experiments live in
``exploregs_plugin.data.depth_supervision``. Kept import-free here so that the trainer can import
one module without pulling in the rest.
"""
