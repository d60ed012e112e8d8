"""Snapshots (consistent copies while the Gaussian set changes) and the render loop's
scheduling and CPU-share sleep accounting (fake clock, no timing assertions)."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest
import torch

from exploregs_plugin.viewer.render_loop import BrowserCamera, DutyCycle, Frame, RenderLoop, ViewSettings
from exploregs_plugin.viewer.snapshot import SnapshotError, SnapshotStore, copy_params


def gaussian_set(n: int, value: float, requires_grad: bool = False) -> dict[str, torch.Tensor]:
    """n Gaussians whose every entry equals ``value`` (so a mix of two sets is detectable)."""
    shapes = {"means": (n, 3), "scales": (n, 3), "quats": (n, 4), "opacities": (n,), "sh0": (n, 1, 3), "shN": (n, 3, 3)}
    return {k: torch.full(s, float(value), requires_grad=requires_grad) for k, s in shapes.items()}


def test_copy_is_detached_and_checked() -> None:
    params = gaussian_set(5, 1.0, requires_grad=True)
    copy = copy_params(params)
    with torch.no_grad():
        params["means"].add_(10.0)
    assert float(copy["means"].max()) == 1.0  # a real copy, not a view
    assert not any(t.requires_grad for t in copy.values())
    bad = gaussian_set(5, 1.0)
    bad["opacities"] = torch.zeros(4)
    with pytest.raises(SnapshotError, match="number of Gaussians"):
        copy_params(bad)
    with pytest.raises(SnapshotError, match="lack"):
        copy_params({"means": torch.zeros(2, 3)})


def test_offer_copies_only_when_requested_and_new() -> None:
    store = SnapshotStore()
    assert store.offer(gaussian_set(2, 0.0), step=0)  # the first offer always publishes
    assert not store.offer(gaussian_set(2, 1.0), step=1)  # nobody asked
    store.request()
    assert not store.offer(gaussian_set(2, 0.0), step=0)  # same step: nothing trained since
    assert not store.requested
    store.request()
    assert store.offer(gaussian_set(3, 2.0), step=2)
    snap = store.latest()
    assert (snap.step, snap.num_gaussians, snap.version, store.copies) == (2, 3, 2, 2)
    assert store.offer(gaussian_set(1, 5.0), step=2, force=True)
    assert store.latest().num_gaussians == 1


def test_snapshot_consistent_while_the_set_changes() -> None:
    """A 'trainer' thread rebuilds the set with a new row count every step, one tensor at a
    time (inconsistent mid-step) and then modifies it in place; it offers only at step
    boundaries. Every snapshot the reader sees must hold one step's set, whole."""
    store = SnapshotStore()
    steps = 300
    gen = torch.Generator().manual_seed(0)
    sizes = torch.randint(1, 50, (steps,), generator=gen).tolist()
    params = gaussian_set(sizes[0], 0.0)
    store.offer(params, step=0, force=True)
    problems: list[str] = []
    seen: set[int] = set()
    done = threading.Event()
    # on a loaded machine the reader thread may not run at all while the writer's loop does:
    # the writer starts once the reader has asked for a snapshot (so one of its steps is
    # copied), and stops once the reader has seen a second step, whatever the scheduling
    asked, saw_change = threading.Event(), threading.Event()

    def reader() -> None:
        while not done.is_set():
            store.request()
            asked.set()
            snap = store.latest()
            rows = {k: v.shape[0] for k, v in snap.params.items()}
            if len(set(rows.values())) != 1:
                problems.append(f"step {snap.step}: rows {rows}")
            for k, v in snap.params.items():
                if not bool((v == snap.step).all()):
                    problems.append(f"step {snap.step}: {k} holds values of another step")
            seen.add(snap.step)
            if len(seen) > 1:
                saw_change.set()

    thread = threading.Thread(target=reader)
    thread.start()
    try:
        asked.wait(timeout=30)
        for step in range(1, steps):
            with torch.no_grad():
                for tensor in params.values():
                    tensor.add_(0.5)  # an optimizer step in place: not a step boundary
            for key, value in gaussian_set(sizes[step], float(step)).items():
                params[key] = value  # densification replaces the tensors one by one
            store.offer(params, step)  # step boundary
        saw_change.wait(timeout=30)
    finally:
        done.set()
        thread.join()
    assert not problems, problems[:5]
    assert len(seen) > 1  # the reader saw the set change
    assert store.copies <= steps  # at most one copy per step, only when asked


def test_duty_cycle_sleep_accounting() -> None:
    duty = DutyCycle()
    assert DutyCycle.sleep_for(0.3, 0.2) == pytest.approx(1.2)  # 0.3 (1 - 0.2) / 0.2
    assert DutyCycle.sleep_for(0.3, 1.0) == 0.0
    for busy in (0.1, 0.4, 0.25):
        duty.record(busy, 0.25)
    assert duty.frames == 3
    assert duty.busy_seconds / (duty.busy_seconds + duty.sleep_seconds) == pytest.approx(0.25)
    for share in (0.0, -0.5, 1.5):
        with pytest.raises(ValueError, match="share"):
            DutyCycle.sleep_for(0.1, share)


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def make_loop(clock: FakeClock, throttled: list[bool], render_seconds: float = 0.1, fail: bool = False):
    store = SnapshotStore()
    store.offer(gaussian_set(2, 0.0), step=0, force=True)
    frames: list[Frame] = []

    def render(snapshot, camera, settings) -> np.ndarray:
        clock.now += render_seconds  # rendering takes this long on the fake clock
        if fail:
            raise RuntimeError("boom")
        return np.zeros((camera.height, camera.width, 3), dtype=np.uint8)

    settings = ViewSettings("rgb", 0, moving_resolution=64, rest_resolution=256, rest_delay=0.5, max_render_share=0.25)
    loop = RenderLoop(store, render, frames.append, settings, throttled=lambda: throttled[0], clock=clock)
    return loop, store, frames


def browser_camera(x: float = 0.0) -> BrowserCamera:
    return BrowserCamera(np.array([1.0, 0.0, 0.0, 0.0]), np.array([x, 0.0, -3.0]), math.radians(60), 800, 400)


def test_render_loop_moving_then_rest_and_cpu_share() -> None:
    clock, throttled = FakeClock(), [True]
    loop, store, frames = make_loop(clock, throttled)
    assert loop.step() is None  # no browser yet
    loop.set_camera(1, browser_camera())
    # Just moved: a low-resolution frame, then sleep so that busy / (busy + sleep) = 0.25.
    assert loop.step() == pytest.approx(0.1 * 0.75 / 0.25)
    assert frames[-1].quality == "moving" and frames[-1].image.shape == (32, 64, 3)
    assert store.requested  # asks the trainer for a fresher snapshot
    assert loop.step() is None  # still moving recently, nothing new to show
    clock.now += 0.5
    loop.step()  # the camera has been still for rest_delay: the sharp frame
    assert frames[-1].quality == "rest" and frames[-1].image.shape == (128, 256, 3)
    assert loop.step() is None
    # Training published a newer snapshot: re-render (at rest quality), without throttling now.
    throttled[0] = False
    store.offer(gaussian_set(4, 1.0), step=7)
    assert loop.step() == 0.0
    assert (frames[-1].quality, frames[-1].step, frames[-1].num_gaussians) == ("rest", 7, 4)
    # A settings change re-renders too.
    loop.update_settings(output="alpha")
    assert loop.step() == 0.0 and len(frames) == 4
    assert loop.duty.frames == 4
    assert loop.duty.sleep_seconds == pytest.approx(2 * 0.1 * 3.0)  # only the throttled frames slept


def test_render_loop_serves_views_in_turn_and_survives_errors() -> None:
    clock, throttled = FakeClock(), [False]
    loop, _, frames = make_loop(clock, throttled)
    loop.set_camera(1, browser_camera(0.0))
    loop.set_camera(2, browser_camera(1.0))
    loop.step()
    loop.step()
    assert sorted(f.client_id for f in frames) == [1, 2]
    loop.set_camera(1, browser_camera(0.5))
    loop.remove(2)
    loop.step()
    assert frames[-1].client_id == 1
    assert loop.step() is None

    failing, _, none_sent = make_loop(FakeClock(), [False], fail=True)
    failing.set_camera(1, browser_camera())
    assert failing.step() == 0.0  # the failure is reported, the loop goes on
    assert failing.errors == 1 and not none_sent
    assert failing.step() is None  # and does not retry the same frame in a busy loop


def test_render_thread_delivers_a_frame() -> None:
    clock, throttled = FakeClock(), [False]
    loop, _, frames = make_loop(clock, throttled)
    delivered = threading.Event()
    original = loop._send
    loop._send = lambda frame: (original(frame), delivered.set())
    loop.start()
    try:
        loop.set_camera(1, browser_camera())
        assert delivered.wait(timeout=20.0)
    finally:
        loop.stop()
    assert frames and frames[0].client_id == 1
