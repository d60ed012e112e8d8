"""The first step whose loss or parameters went non-finite, recorded on the device.

Reading a value that lives on a GPU (``float``, ``bool``, ``.item()``, ``.cpu()``) makes the host
wait until every kernel queued before it has run, so the host and the GPU stop overlapping. A
check of the loss and of the parameters at every step did that twice a step (docs/gpu.md). Here a
step only updates a record on the device with ``torch.where``: the step that first went bad and
what went bad there (the step's loss and terms, or each parameter's non-finite rows and the
Gaussian count at that step). The trainer reads the record at its read points (the log line,
evaluations, checkpoints, the end of the run, and a step that failed), one read for the whole
record, and :meth:`NonFiniteWatch.error` gives the error that step itself would have raised.
"""

from __future__ import annotations

import torch
from torch import Tensor

from exploregs_plugin.kernels import cpp_problem, extension
from exploregs_plugin.rasterizer.composite import thread_budget

PART_PREFIX = "deformation."
"""A model part's parameters (a deformation field's) have no Gaussian rows: their values are counted."""


class NonFiniteError(RuntimeError):
    """Training produced a NaN or inf (in the loss or in a parameter) at step ``step``."""

    def __init__(self, message: str, step: int | None = None) -> None:
        super().__init__(message)
        self.step = step


def nonfinite_count(name: str, p: Tensor) -> Tensor:
    """How much of ``p`` is non-finite: its Gaussian rows with a NaN or inf (a 0-dim long tensor),
    or, for a model part's parameter, its values."""
    with torch.no_grad():  # no detach: nothing here is recorded (each operator costs a dispatch)
        if p.ndim > 1 and not name.startswith(PART_PREFIX):
            # p * 0 is 0 for a finite value and NaN for a NaN or an inf, so a row's sum of it is NaN
            # exactly when the row holds one, and cannot overflow (finite float32 values can: 3.4e38
            # twice). A float32 product and sum instead of a float64 copy and its sum: Default's beer
            # step 0.6 ms shorter at 11.7k Gaussians (docs/training.md); isfinite's three passes and
            # an any were 8% of a beer step at 45k Gaussians (docs/rasterizer.md).
            return p.shape[0] - torch.isfinite((p * 0.0).sum(dim=tuple(range(1, p.ndim)))).sum()
        return p.numel() - torch.isfinite(p).sum()


def nonfinite_counts(named: list[tuple[str, Tensor]]) -> Tensor:
    """:func:`nonfinite_count` of every tensor of ``named``, as a [K] long tensor on their device.

    On the CPU, where the compiled kernels build, one call counts them all (an integer test of each
    value's exponent bits: the same counts, no float sums, and none of the five operators per
    tensor of the torch path)."""
    first = named[0][1]
    if first.device.type == "cpu" and cpp_problem() is None \
            and all(p.dtype in (torch.float32, torch.float64) for _, p in named):
        by_row = [int(p.ndim > 1 and not name.startswith(PART_PREFIX)) for name, p in named]
        # the parameters as they are: the kernel reads their values and records nothing (no detach)
        return extension().nonfinite_counts([p for _, p in named], by_row, thread_budget())
    return torch.stack([nonfinite_count(name, p) for name, p in named])


class NonFiniteWatch:
    """Device-side record of the first non-finite loss and the first non-finite parameters.

    :meth:`loss` and :meth:`params` are called every step and never read the device; :meth:`error`
    reads the record once. Steps after the first bad one leave the record as it is, so the error
    names the step where the run first went bad, however late it is read."""

    def __init__(self) -> None:
        self._loss_step: Tensor | None = None  # long, -1 until a loss is non-finite
        self._loss_values: dict[str, Tensor] = {}  # that step's totals (loss and terms)
        self._param_step: Tensor | None = None  # long, -1 until a parameter is non-finite
        self._param_counts: Tensor | None = None  # [K] each parameter's non-finite rows (values) then
        self._param_gaussians: Tensor | None = None  # the Gaussian count then
        self._param_names: list[str] = []

    def loss(self, step: int, totals: dict[str, Tensor]) -> None:
        """Record ``totals`` (0-dim float64: ``loss``, ``psnr`` and the terms) if this is the first
        step whose loss is non-finite."""
        loss = totals["loss"]
        if self._loss_step is None:
            self._loss_step = torch.full((), -1, dtype=torch.long, device=loss.device)
        first = ~torch.isfinite(loss) & (self._loss_step < 0)
        self._loss_step = torch.where(first, step, self._loss_step)
        self._loss_values = {k: torch.where(first, v, self._loss_values[k] if k in self._loss_values
                                            else torch.zeros_like(v)) for k, v in totals.items()}

    def params(self, step: int, named: list[tuple[str, Tensor]], num_gaussians: int) -> None:
        """Record each parameter's non-finite rows (a part's: values) and the Gaussian count if
        this is the first step with a non-finite parameter. ``named``: every trained tensor, in a
        fixed order (the error names the first bad one)."""
        if not named:
            return
        counts = nonfinite_counts(named)
        if self._param_step is None:  # the trained tensors' names are fixed for a run
            self._param_names = [name for name, _ in named]
            self._param_step = torch.full((), -1, dtype=torch.long, device=counts.device)
            self._param_counts = torch.zeros_like(counts)
            self._param_gaussians = torch.zeros((), dtype=torch.long, device=counts.device)
        first = (counts > 0).any() & (self._param_step < 0)
        self._param_step = torch.where(first, step, self._param_step)
        self._param_counts = torch.where(first, counts, self._param_counts)
        self._param_gaussians = torch.where(first, num_gaussians, self._param_gaussians)

    def error(self) -> NonFiniteError | None:
        """The error of the first step that went non-finite (its loss first, where the loss and
        the parameters went bad at the same step), or None. One read of the device."""
        parts: list[Tensor] = []
        if self._loss_step is not None:
            parts += [self._loss_step.reshape(1)] + [v.reshape(1) for v in self._loss_values.values()]
        if self._param_step is not None:
            parts += [self._param_step.reshape(1), self._param_gaussians.reshape(1), self._param_counts.reshape(-1)]
        if not parts:
            return None
        values = torch.cat([p.to(torch.float64) for p in parts]).tolist()
        loss_step = param_step = -1
        if self._loss_step is not None:
            loss_step = int(values[0])
            loss = dict(zip(self._loss_values, values[1:1 + len(self._loss_values)]))
            values = values[1 + len(self._loss_values):]
        if self._param_step is not None:
            param_step, gaussians, counts = int(values[0]), int(values[1]), values[2:]
        if loss_step >= 0 and (param_step < 0 or loss_step <= param_step):
            terms = ", ".join(f"{k}={v:.4g}" for k, v in loss.items() if k not in ("loss", "psnr"))
            return NonFiniteError(f"step {loss_step}: the loss is {loss['loss']} (terms: {terms})", loss_step)
        if param_step < 0:
            return None
        name, count = next((n, int(c)) for n, c in zip(self._param_names, counts) if c > 0)
        if name.startswith(PART_PREFIX):
            return NonFiniteError(f"step {param_step}: parameter '{name}' has {count} non-finite values", param_step)
        return NonFiniteError(f"step {param_step}: parameter '{name}' has non-finite values in {count} of "
                              f"{gaussians} Gaussians", param_step)
