"""bench/auto_cap.py: the replay of MCMC's automatic cap on a traced run stops where a real
automatic run stops (same seed: the two runs are the same run until that refinement)."""

from __future__ import annotations

import json
from dataclasses import replace

from exploregs_plugin.bench.components import auto_cap
from exploregs_plugin.scripts.train import parse_config
from exploregs_plugin.engine.trainer import Trainer

TINY = ["exploregs-mcmc", "--data", "builtin:tiny", "--max-steps", "150", "--schedule.min-refine-every", "10",
        "--num-threads", "1"]


def test_replay_stops_where_an_automatic_run_stops(tmp_path):
    out = tmp_path / "trace.json"
    auto_cap.trace(out, 120, TINY + ["--strategy.cap-max", "100000"])
    data = json.loads(out.read_text())
    assert len(data["rows"]) == 120 and data["refine_every"] == 10
    assert data["refinements"] and all(c["added"] > 0 for s, c in data["refinements"] if s < 100)  # it grew
    stop, count = auto_cap.replay(data, 0.05, 2, 2)
    assert stop is not None and 20 < stop < 120
    # the automatic run with the same constants
    config = parse_config(TINY + ["--strategy.cap-max", "auto", "--strategy.auto-span", "2"])
    config = replace(config, run_dir=tmp_path / "auto", quiet=True, tensorboard=False, eval_count=0,
                     save_eval_images=False)
    trainer = Trainer(config)
    trainer.train()
    state = trainer.pipeline.strategy_state
    assert state["auto_cap"] == count
    # and the traced run's count before the stop is the automatic run's count from then on
    assert [r[3] for r in data["rows"] if r[0] == stop - 1] == [count]
    assert trainer.pipeline.model.num_gaussians == count  # MCMC never prunes: the count stays at the cap


def test_replay_with_a_threshold_the_trace_never_meets_says_beyond(tmp_path):
    rows = [[s, s % 3, 0.1 * 0.9 ** (s // 10), 100 + s] for s in range(100)]  # 10% per 10 steps
    data = {"refine_start_iter": 5, "refine_stop_iter": 90, "refine_every": 10, "rows": rows}
    assert auto_cap.replay(data, 0.05, 1, 2) == (None, None)
    assert auto_cap.replay(data, 0.2, 1, 2) == (30, 129)  # judged from the 2nd window: 20 and 30 below
