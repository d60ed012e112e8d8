"""Blur-Trap diagnostics: gradient branches and their directions, alpha-blending attenuation,
and the figures (``eg-analyze``).

Modules: ``branches`` (per-path gradients of the means), ``directions`` (cosines with the ray
and the optical axis), ``blending`` (per-pixel and per-depth-rank transmittance and screen-space
gradient), ``plots`` (figures and tables), ``sampling`` (views and iterations), ``probing`` (a
short run that stops to probe, through a training callback), ``tensorboard`` (the branch-gradient
training callback), ``branch_ablation`` (the model variant with position paths switched off, method
``exploregs-branch-ablation``), ``ablations`` (the paper's ablations as eg-bench entries),
``depth_degradation`` (the degraded depth maps of the depth-supervision experiments). The
runbooks and scripts that use them live beside the package in ``experiments/``.
"""
