"""The old name of :mod:`.into_gsplat`, kept so that an old import fails with directions.

Its classes were gsplat strategies with exploration fields of their own (``n_split``, ``n_seed``,
``noise_lr``, ...); the new ones hold our operators' configs instead (``splitting.n_split``,
``seeding.n_seed``, ``noise.lr``), so an alias would import and then fail at the first constructor
call with an unexpected keyword. One ImportError that names the new module, classes and fields
is what a user of the old import can act on.
"""

raise ImportError(
    "exploregs_plugin.integrations.gsplat is now exploregs_plugin.integrations.into_gsplat: SeedSplitStrategy -> "
    "GsplatSeedSplitStrategy, SeedStrategy -> GsplatSeedStrategy, SplitStrategy -> GsplatSplitStrategy, RayStrategy "
    "-> GsplatRayStrategy, MCMCRayStrategy -> GsplatMCMCRayStrategy; their exploration fields are the operators' own "
    "(n_split -> splitting.n_split, split_every -> splitting.every, n_seed -> seeding.n_seed, seed_prune_scale3d -> "
    "seeding.prune_scale3d, seed_min_scale -> seeding.min_scale, seed_center -> scene_center, noise_lr / noise_gate_k "
    "/ noise_gate_t -> noise.lr / noise.gate_k / noise.gate_t); see docs/integrations.md"
)
