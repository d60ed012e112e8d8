"""Two source trees' runs from the same initial Gaussians: where does a training difference begin?

Fresh runs of two trees part at the first step whenever the initial parameters differ by a rounding
(for example the initial scales from other neighbour distances), and training turns that rounding
into seed-sized differences. Saving one tree's initial parameters and training the other tree from
them removes that part: what is left is the code's own. Run each half with the tree it names on
``PYTHONPATH`` (the script uses only ``parse_config`` and the trainer's setup, which both trees have):

    PYTHONPATH=OLD python experiments/determinism/same_start.py save init.pt -- eg-train's arguments
    PYTHONPATH=NEW python experiments/determinism/same_start.py train init.pt -- eg-train's arguments
    PYTHONPATH=NEW python experiments/determinism/same_start.py steps init.pt out.pt 3 -- arguments
    python experiments/determinism/same_start.py compare a.pt b.pt

``save`` writes the initial parameters of the run those arguments set up (nothing trained);
``train`` sets up the run, replaces its initial parameters by the file's and trains it to the end
(``metrics.json`` and checkpoints in its run folder, as eg-train); ``steps`` trains only N steps from
them and saves each step's parameters and loss; ``compare`` says, for two checkpoints or two
``steps`` files, which tensors are the same bits and the largest difference of the others.
"""

from __future__ import annotations

import sys

import torch


def _setup(argv: list[str]):
    from exploregs_plugin.scripts.train import parse_config

    return parse_config(argv).setup()


def _load_initial(trainer, path: str) -> None:
    initial = torch.load(path)
    params = trainer.pipeline.params
    if set(initial) != set(params):
        raise SystemExit(f"{path}: holds {sorted(initial)}, the run has {sorted(params)}")
    with torch.no_grad():
        for name, value in params.items():
            if value.shape != initial[name].shape:
                raise SystemExit(f"{path}: {name} is {tuple(initial[name].shape)}, the run's {tuple(value.shape)}")
            value.copy_(initial[name])


def _params(trainer) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in trainer.pipeline.params.items()}


def _tensors(path: str) -> list[dict[str, torch.Tensor]]:
    """A checkpoint's parameters, or each step's of a ``steps`` file."""
    data = torch.load(path, weights_only=False)
    if "params" in data:
        return [data["params"]]
    return [step["params"] for step in data["steps"]]


def compare(a: str, b: str) -> None:
    for index, (x, y) in enumerate(zip(_tensors(a), _tensors(b))):
        parts = []
        for name in x:
            if x[name].shape != y[name].shape:
                parts.append(f"{name} {tuple(x[name].shape)} vs {tuple(y[name].shape)}")
            elif torch.equal(x[name], y[name]):
                parts.append(f"{name} same bits")
            else:
                parts.append(f"{name} differs by at most {float((x[name] - y[name]).abs().max()):.3g}")
        print(f"{index}: " + ", ".join(parts))


def main(argv: list[str]) -> None:
    if not argv or argv[0] not in ("save", "train", "steps", "compare"):
        raise SystemExit(__doc__)
    if argv[0] == "compare":
        compare(argv[1], argv[2])
        return
    split = argv.index("--")
    own, run_argv = argv[1:split], argv[split + 1:]
    if argv[0] == "save":
        torch.save(_params(_setup(run_argv)), own[0])
        return
    trainer = _setup(run_argv)
    _load_initial(trainer, own[0])
    if argv[0] == "train":
        metrics = trainer.train()
        print(f"test PSNR {metrics['psnr']:.3f} dB, LPIPS {metrics.get('lpips', float('nan')):.4f}, "
              f"{metrics['num_gaussians']} Gaussians")
        return
    out, count = own[1], int(own[2])
    steps = []
    for step in range(count):
        loss = trainer.pipeline.train_step(step)["loss"]
        steps.append({"params": _params(trainer), "loss": float(loss)})
    torch.save({"steps": steps}, out)


if __name__ == "__main__":
    main(sys.argv[1:])
