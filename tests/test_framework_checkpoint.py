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


def test_enospc_inside_torch_save_is_one_clear_error_and_keeps_the_old_checkpoint(tmp_path, monkeypatch):
    # A full disk during torch.save comes out of torch as a RuntimeError ("unexpected pos ...")
    # whose context is the file's OSError: the atomic save must catch it like an OSError.
    good = ck.save_checkpoint(tmp_path, 10, _payload(10), keep_last=3)
    real_open = open

    class FullDisk:
        def __init__(self, f):
            self.f, self.written = f, 0

        def write(self, data):
            self.written += len(data)
            if self.written > 100:
                raise OSError(errno.ENOSPC, "No space left on device")
            return self.f.write(data)

        def __getattr__(self, name):
            return getattr(self.f, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

    def full_open(path, mode="r", *args, **kwargs):
        f = real_open(path, mode, *args, **kwargs)
        return FullDisk(f) if ".tmp-" in str(path) else f  # the checkpoint's temporary file

    monkeypatch.setattr("builtins.open", full_open)
    with pytest.raises(ck.CheckpointError) as err:
        ck.save_checkpoint(tmp_path, 20, _payload(20), keep_last=3)
    monkeypatch.setattr("builtins.open", real_open)
    assert isinstance(err.value.__cause__, RuntimeError)  # torch's own error, caught
    assert str(err.value) == f"could not write checkpoint {ck.checkpoint_path(tmp_path, 20)}: No space left on device"
    assert [p.name for p in (tmp_path / "checkpoints").iterdir()] == [good.name]
    assert ck.load_checkpoint(good)["step"] == 10


def test_a_truncated_newest_checkpoint_gives_way_to_the_previous_one(tmp_path):
    (tmp_path / "config.yml").write_text("a run\n")
    for step in (10, 20, 30):
        ck.save_checkpoint(tmp_path, step, _payload(step), keep_last=3)
    newest = ck.checkpoint_path(tmp_path, 30)
    newest.write_bytes(newest.read_bytes()[:200])  # a copy cut short, a disk that lost the tail
    notes: list[str] = []
    run_dir, path, payload = ck.load_run_checkpoint(tmp_path, notes.append)
    assert (run_dir, path, payload["step"]) == (tmp_path, ck.checkpoint_path(tmp_path, 20), 20)
    assert notes == [f"note: checkpoint step-0000030.pt of {tmp_path} cannot be read (truncated or corrupt); "
                     f"using the previous good one, step-0000020.pt"]
    # a checkpoint named explicitly is read as it is: its own error
    with pytest.raises(ck.CheckpointError, match="step-0000030.pt is unreadable or corrupt"):
        ck.load_run_checkpoint(newest)
    for step in (10, 20):
        ck.checkpoint_path(tmp_path, step).write_bytes(b"")
    with pytest.raises(ck.CheckpointError, match="no checkpoint of .* can be read .*start the run again"):
        ck.load_run_checkpoint(tmp_path, notes.append)


def test_a_folder_that_is_not_a_run_is_named_as_such(tmp_path):
    outputs = tmp_path / "outputs"
    run = outputs / "tiny" / "exploregs-default" / "2026-11-25_010203"
    ck.save_checkpoint(run, 5, _payload(5), keep_last=1)
    (run / "config.yml").write_text("a run\n")
    with pytest.raises(ck.CheckpointError) as err:
        ck.resolve_run(outputs)
    assert str(err.value) == (f"{outputs} is not a run folder (it has no config.yml): pass a folder that eg-train "
                              f"wrote, outputs/<scene>/<method>/<timestamp>, or a checkpoint file in one; it holds "
                              f"1 run(s), the newest {run}")
    assert ck.resolve_run(run) == (run, ck.checkpoint_path(run, 5))


def test_two_runs_asking_for_one_folder_at_once_get_two(tmp_path):
    import threading

    from exploregs_plugin.io.atomic import create_new_folder

    wanted = tmp_path / "outputs" / "scene" / "method" / "2026-11-25_010203"
    start = threading.Barrier(6)
    got: list = []

    def claim():
        start.wait()
        got.append(create_new_folder(wanted))

    threads = [threading.Thread(target=claim) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(p.name for p in got) == sorted([wanted.name] + [f"{wanted.name}-{n}" for n in range(2, 7)])
    assert all(p.is_dir() for p in got)
