"""The machine a run uses: ``device`` (``--device``, moving state between devices, the run's
generator), ``distributed`` (the data-parallel ``World`` of ranks and its collectives,
``MachineConfig``), ``threads`` (thread counts from the CPUs other processes leave idle; the
passive OpenMP wait that the package sets before torch loads) and ``lazy_names`` (a package's
names imported on first use, so that a command's --help does not load what it never runs). Nothing here imports torch at
package import, so ``exploregs_plugin/__init__.py`` can set the OpenMP environment first."""
