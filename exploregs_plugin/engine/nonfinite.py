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
    """:func:`nonfinite_count` of every tensor of ``named``, as a [K] long tensor on their device
    (the torch path: on the CPU the compiled watch counts them all in one call, with an integer
    test of each value's exponent bits, see :class:`NonFiniteWatch`)."""
    return torch.stack([nonfinite_count(name, p) for name, p in named])


def _compiled(tensors: list[Tensor], dtypes: tuple[torch.dtype, ...]) -> bool:
    """Whether the compiled watch takes ``tensors``: on the CPU, where the kernels build."""
    return tensors[0].device.type == "cpu" and cpp_problem() is None and all(t.dtype in dtypes for t in tensors)


class NonFiniteWatch:
    """Device-side record of the first non-finite loss and the first non-finite parameters.

    :meth:`loss` and :meth:`params` are called every step and never read the device; :meth:`error`
    reads the record once. Steps after the first bad one leave the record as it is, so the error
    names the step where the run first went bad, however late it is read. On the CPU each call is
    one compiled operator that updates its record in place (it was nine: a test, a comparison and
    a ``where`` per recorded value)."""

    def __init__(self) -> None:
        # float64 [1 + K]: the first step whose loss is non-finite (-1 until one), then that step's
        # totals of the keys (the loss, the PSNR and the terms)
        self._loss_record: Tensor | None = None
        self._loss_keys: tuple[str, ...] = ()
        # long [2 + K]: the first step with a non-finite parameter (-1 until one), the Gaussian count
        # then, and each trained tensor's non-finite rows (a part's: values) then
        self._param_record: Tensor | None = None
        self._param_names: list[str] = []

    def loss(self, step: int, totals: dict[str, Tensor]) -> None:
        """Record ``totals`` (0-dim float64: ``loss``, ``psnr`` and the terms) if this is the first
        step whose loss is non-finite."""
        keys, values = tuple(totals), list(totals.values())
        if keys != self._loss_keys:
            self._loss_record = self._rekeyed(keys, values[0].device)
        if _compiled(values, (torch.float64,)):
            extension().watch_loss_(values, self._loss_record, step)
            return
        record = self._loss_record
        first = ~torch.isfinite(values[0]) & (record[0] < 0)
        now = torch.stack([torch.full((), float(step), dtype=torch.float64, device=record.device), *values])
        self._loss_record = torch.where(first, now, record)

    def _rekeyed(self, keys: tuple[str, ...], device: torch.device) -> Tensor:
        """A loss record for ``keys`` that keeps what the old one recorded (its step and the values
        of the keys both have); a run's keys are fixed, so this is its first step."""
        record = torch.zeros(1 + len(keys), dtype=torch.float64, device=device)
        record[0] = -1.0
        if self._loss_record is not None:
            record[0] = self._loss_record[0]
            for i, key in enumerate(keys):
                if key in self._loss_keys:
                    record[1 + i] = self._loss_record[1 + self._loss_keys.index(key)]
        self._loss_keys = keys
        return record

    def params(self, step: int, named: list[tuple[str, Tensor]], num_gaussians: int) -> None:
        """Record each parameter's non-finite rows (a part's: values) and the Gaussian count if
        this is the first step with a non-finite parameter. ``named``: every trained tensor, in a
        fixed order (the error names the first bad one)."""
        if not named:
            return
        if self._param_record is None:  # the trained tensors' names are fixed for a run
            self._param_names = [name for name, _ in named]
            self._param_record = torch.full((2 + len(named),), -1, dtype=torch.long, device=named[0][1].device)
        tensors = [p for _, p in named]
        if _compiled(tensors, (torch.float32, torch.float64)):
            by_row = [int(p.ndim > 1 and not name.startswith(PART_PREFIX)) for name, p in named]
            # the parameters as they are: the kernel reads their values and records nothing (no detach)
            extension().watch_params_(tensors, by_row, self._param_record, step, num_gaussians, thread_budget())
            return
        counts = nonfinite_counts(named)
        record = self._param_record
        first = (counts > 0).any() & (record[0] < 0)
        now = torch.cat([torch.tensor([step, num_gaussians], dtype=torch.long, device=record.device), counts])
        self._param_record = torch.where(first, now, record)

    def error(self) -> NonFiniteError | None:
        """The error of the first step that went non-finite (its loss first, where the loss and
        the parameters went bad at the same step), or None. One read of the device."""
        parts = [r.to(torch.float64) for r in (self._loss_record, self._param_record) if r is not None]
        if not parts:
            return None
        values = torch.cat(parts).tolist()
        loss_step = param_step = -1
        if self._loss_record is not None:
            loss_step = int(values[0])
            loss = dict(zip(self._loss_keys, values[1:1 + len(self._loss_keys)]))
            values = values[1 + len(self._loss_keys):]
        if self._param_record is not None:
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
