"""Benchmarks and experiment harnesses, in one home.

eg-bench (methods x scenes x seeds through the normal trainer, the paper's tables and plots)::

    from exploregs_plugin.bench.presets import preset
    from exploregs_plugin.bench.report import run_bench
    payload = run_bench(preset("quick"), Path("bench-quick"))

and the component benchmarks in ``components/``, each a script that prints a table (``python -m
exploregs_plugin.bench.components.rasterizer``, ``.train_step``, ``.opcost``, ``.viewer``, ...).
Nothing is imported here, so a component benchmark does not load the trainer. The paper's
ablations as bench entries are research code: ``exploregs_plugin.analysis.ablations``.
"""
