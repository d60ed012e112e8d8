"""The component benchmarks: each a script that prints a table, ``python -m
exploregs_plugin.bench.components.NAME`` (the rasterizer, a training step, operators per step, op costs, the viewer,
scale, memory, threads beside busy processes, the densification statistic at coarse-to-fine
levels, MCMC's automatic cap on a traced run, posing against reference poses, the export formats
and smaller splats). Nothing is imported here, so a benchmark does not load the trainer."""
