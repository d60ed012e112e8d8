"""Checkpoints: atomic writes, retention, clear errors."""

import errno

import pytest
import torch

from exploregs_plugin.io import checkpoint as ck


def _payload(step: int) -> dict:
    return {"step": step, "params": {"means": torch.full((4, 3), float(step))}}


def test_keep_last_and_latest(tmp_path):
    for step in (10, 20, 30, 40):
        ck.save_checkpoint(tmp_path, step, _payload(step), keep_last=2)
    names = [p.name for p in ck.list_checkpoints(tmp_path)]
    assert names == ["step-0000030.pt", "step-0000040.pt"]
    latest = ck.load_checkpoint(ck.latest_checkpoint(tmp_path))
    assert latest["step"] == 40
    assert torch.equal(latest["params"]["means"], torch.full((4, 3), 40.0))


@pytest.mark.parametrize("failure", [OSError(errno.ENOSPC, "No space left on device"), KeyboardInterrupt()])
def test_interrupted_write_never_replaces_good_checkpoint(tmp_path, monkeypatch, failure):
    good = ck.save_checkpoint(tmp_path, 100, _payload(100), keep_last=3)
    good_bytes = good.read_bytes()
    real_save = torch.save

    def half_write(obj, f, *args, **kwargs):
        # write a partial, truncated payload, then fail midway as a full disk or Ctrl-C would
        real_save(obj, f)
        f.truncate(17)
        raise failure

    monkeypatch.setattr(torch, "save", half_write)
    expected = ck.CheckpointError if isinstance(failure, OSError) else KeyboardInterrupt
    with pytest.raises(expected):
        ck.save_checkpoint(tmp_path, 100, _payload(999), keep_last=3)
    with pytest.raises(expected):
        ck.save_checkpoint(tmp_path, 200, _payload(200), keep_last=3)
    monkeypatch.setattr(torch, "save", real_save)
    assert good.read_bytes() == good_bytes
    assert [p.name for p in (tmp_path / "checkpoints").iterdir()] == ["step-0000100.pt"]  # no temp files left
    assert ck.load_checkpoint(ck.latest_checkpoint(tmp_path))["step"] == 100


def test_corrupt_and_missing_checkpoints_are_named(tmp_path):
    with pytest.raises(ck.CheckpointError, match="no checkpoints"):
        ck.latest_checkpoint(tmp_path)
    bad = ck.checkpoint_path(tmp_path, 5)
    bad.parent.mkdir(parents=True)
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(ck.CheckpointError, match="step-0000005.pt"):
        ck.load_checkpoint(bad)
    with pytest.raises(ck.CheckpointError, match="neither a run folder"):
        ck.resolve_run(tmp_path / "missing")
    run_dir, path = ck.resolve_run(bad)
    assert run_dir == tmp_path and path == bad


@pytest.mark.parametrize("failure", [OSError(errno.ENOSPC, "No space left on device"), KeyboardInterrupt()])
def test_interrupted_text_write_keeps_the_old_file(tmp_path, monkeypatch, failure):
    # metrics.json, config.yml, bench tables and states all go through atomic_write_text
    from exploregs_plugin.io import atomic

    path = tmp_path / "run" / "metrics.json"
    atomic.atomic_write_text(path, '{"psnr": 20.0}')
    assert path.read_text() == '{"psnr": 20.0}'

    def failing_replace(src, dst):
        raise failure

    monkeypatch.setattr(atomic.os, "replace", failing_replace)
    with pytest.raises(type(failure)):
        atomic.atomic_write_text(path, '{"psnr": 30.0}')
    assert path.read_text() == '{"psnr": 20.0}'
    assert [p.name for p in path.parent.iterdir()] == ["metrics.json"]  # no temp file left
