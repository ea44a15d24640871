"""Progress bars of the long commands (tree builds, calibration, replay, start-up).

tqdm draws them: one small dependency-free package, the field's common
choice, that writes to stderr and turns itself off when stderr is not a
terminal (``disable=None``), so logs, pipes and CI stay clean; ``--quiet``
turns it off on a terminal too.
"""

from __future__ import annotations

from typing import Any

from tqdm import tqdm

_FRACTION_STEPS = 1000


def bar(label: str, total: int | None, *, quiet: bool = False, unit: str = "it") -> Any:
    """A counting bar on stderr: ``with bar(...) as b: b.update()``; silent off a TTY."""
    return tqdm(
        total=total, desc=label, unit=unit, disable=True if quiet else None, dynamic_ncols=True
    )


class FractionBar:
    """A bar fed with fractions in [0, 1] (``GridTree.build``'s ``progress``), and
    with a message that names the phase (``(fraction, message)`` callbacks)."""

    def __init__(self, label: str, *, quiet: bool = False) -> None:
        self._bar = tqdm(
            total=_FRACTION_STEPS,
            desc=label,
            disable=True if quiet else None,
            dynamic_ncols=True,
            bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed}<{remaining}{postfix}",
        )

    def __call__(self, fraction: float, message: str | None = None) -> None:
        n = round(min(max(float(fraction), 0.0), 1.0) * _FRACTION_STEPS)
        if message is not None:
            self._bar.set_postfix_str(message, refresh=False)
        if n > self._bar.n:
            self._bar.update(n - self._bar.n)

    def close(self) -> None:
        self._bar.close()

    def __enter__(self) -> FractionBar:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
