"""Shared test fixtures.

The whole session uses one cache directory (``$EXPLOREGS_CACHE`` points into the session's
tmp dir), so ``builtin:tiny`` is generated once per session and no test writes to ~/.cache.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# The package before torch: it asks OpenMP for passive waiting, which the runtime reads once, when
# torch loads it (runtime/threads.py). Imported after torch, the tests' own process would spin its
# threads at the end of every parallel region, as no command of the package does: CPU time that
# tells nothing and, on a busy machine, a collapse of every two-thread run in this process.
import exploregs_plugin  # noqa: F401,I001
import torch  # noqa: E402

SHARED_SCENES = Path(__file__).resolve().parents[1].parent / "shared" / "scenes"
"""Real captured scenes next to the repository (tests that use them skip when absent)."""


def _selects_cuda(markexpr: str) -> bool:
    """Whether a ``-m`` expression picks the CUDA tests (``cuda``, ``cuda and not slow``) rather
    than leaving them out (``not cuda``) or not naming them (the default ``not slow``)."""
    tokens = markexpr.replace("(", " ").replace(")", " ").split()
    return any(t == "cuda" and (i == 0 or tokens[i - 1] != "not") for i, t in enumerate(tokens))


def pytest_configure(config: pytest.Config) -> None:
    """The default suite is the CPU contract (bit-identical results across thread counts, resumes
    and seeds; the compiled CPU backend), so on a machine with a GPU it still runs on the CPU:
    otherwise ``--device auto`` would put every test's run, and every command a test starts, on
    CUDA, where atomic adds make runs differ bit for bit. The CUDA contract is
    ``python -m pytest -m cuda`` (tests/test_cuda.py), which keeps the GPU visible. Hidden through
    the environment before anything has initialised CUDA, so subprocesses inherit it."""
    cuda = _selects_cuda(config.getoption("markexpr") or "")
    if not cuda:
        os.environ["CUDA_VISIBLE_DEVICES"] = ""
    if not cuda or not torch.cuda.is_available():
        # gsplat builds its CUDA kernels on first import wherever it finds nvcc (minutes, and a second
        # process importing it meanwhile deletes the half-built folder); the CPU suite uses only its
        # pure-torch parts
        os.environ["CUDA_HOME"] = "/nonexistent-cuda"


@pytest.fixture(scope="session", autouse=True)
def exploregs_cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The session's cache root (``$EXPLOREGS_CACHE``): built-in scenes, derived images."""
    root = tmp_path_factory.mktemp("exploregs-cache")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("EXPLOREGS_CACHE", str(root))
        yield root


@pytest.fixture(scope="session")
def tiny_scene_dir(exploregs_cache: Path) -> Path:
    """Folder of the built-in ``tiny`` scene (COLMAP text + depths + masks), made once.

    Read-only by convention: tests that modify a dataset copy it first."""
    from exploregs_plugin.data.builtin.presets import ensure_builtin

    return ensure_builtin("tiny", exploregs_cache / "scenes")


@pytest.fixture(scope="session")
def tiny_run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished 60-step Default run on ``builtin:tiny``, for tests that read a trained run (and
    load it afresh, so the run folder itself is never changed)."""
    from exploregs_plugin.engine.trainer import TrainerConfig

    run_dir = tmp_path_factory.mktemp("tiny-run")
    TrainerConfig(data="builtin:tiny", max_steps=60, run_dir=run_dir, quiet=True, tensorboard=False,
                  eval_count=1, save_eval_images=False).setup().train()
    return run_dir


@pytest.fixture()
def tiny_dm(tiny_scene_dir: Path):
    """A fresh DataManager on ``builtin:tiny`` (the scene itself is cached for the session)."""
    from exploregs_plugin.data import DataManagerConfig

    return DataManagerConfig(data="builtin:tiny").setup()


@pytest.fixture()
def sigint_as_in_a_terminal():
    """SIGINT raises KeyboardInterrupt for the test, as in a terminal's foreground, restored after.
    A test that sends SIGINT depends on it: a shell's script that starts the tests in the
    background (``bash -c 'python -m pytest ... &'``) starts Python with SIGINT ignored, which
    Python keeps and the processes it starts inherit (a handler set here reaches them as the
    default, which Python turns into KeyboardInterrupt again)."""
    import signal

    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, signal.SIG_DFL if before is None else before)  # None: set outside Python


@pytest.fixture()
def ctrl_c_after_step(monkeypatch: pytest.MonkeyPatch, sigint_as_in_a_terminal):
    """``arm(step)`` makes the next training send a real SIGINT (Ctrl-C) to this process right
    after that step, which the trainer handles at the step boundary; ``disarm()`` undoes it."""
    import os
    import signal

    from exploregs_plugin.engine.pipeline import Pipeline

    real_step = Pipeline.train_step

    class Switch:
        def arm(self, at_step: int) -> None:
            def step_then_ctrl_c(pipeline, step):
                out = real_step(pipeline, step)
                if step == at_step:
                    os.kill(os.getpid(), signal.SIGINT)
                return out

            monkeypatch.setattr(Pipeline, "train_step", step_then_ctrl_c)

        def disarm(self) -> None:
            monkeypatch.setattr(Pipeline, "train_step", real_step)

    return Switch()


@pytest.fixture(params=["torch", "cpp"])
def raster_backend(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Runs a test once per CPU renderer: every ``rasterize`` call in it draws with this backend,
    whatever its settings say (``auto`` included). The compiled one is skipped, with the reason,
    only on a machine that cannot build it (test_rasterizer_cpp.py fails where it should build)."""
    import importlib

    from exploregs_plugin.rasterizer.cpp_backend import cpp_problem

    # the module (the package's own name `rasterize` is the function)
    rasterize_module = importlib.import_module("exploregs_plugin.rasterizer.rasterize")

    if request.param == "cpp" and cpp_problem() is not None:
        pytest.skip(f"the cpp backend cannot build here: {cpp_problem()}")
    monkeypatch.setattr(rasterize_module, "resolve_backend", lambda settings, device: request.param)
    return request.param


@pytest.fixture()
def one_thread():
    """torch at one thread for the test (restored after): on tensors of a few hundred rows one
    thread is fastest, and much faster than two on a CPU that another process keeps busy."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
