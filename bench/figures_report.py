"""How a benchmark reports on the command line: the table of its figures, the exit code of a
run that failed or was interrupted, and the ``--repeats`` option of the timing benchmarks."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator, Mapping
from contextlib import contextmanager


def print_figures(figures: Mapping[str, float]) -> None:
    """One line a figure: the name padded to the longest, the value with 3 decimals."""
    width = max(len(k) for k in figures)
    for name, value in figures.items():
        print(f"  {name:<{width}}  {value:12.3f}")


@contextmanager
def exit_codes(prog: str, error: type[Exception], *, interrupted: str) -> Iterator[None]:
    """Around a benchmark's run in its ``main``: ``error`` is printed as ``<prog>: <message>``
    and exits 1; Ctrl-C prints ``<prog>: interrupted (<interrupted>)`` and exits 130."""
    try:
        yield
    except error as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        raise SystemExit(1) from None
    except KeyboardInterrupt:
        print(f"{prog}: interrupted ({interrupted})", file=sys.stderr)
        raise SystemExit(130) from None


def parse_repeats(parser: argparse.ArgumentParser, argv: list[str] | None, *, runs: int,
                  min_runs: int, what: str) -> argparse.Namespace:
    """Add ``--repeats`` (``what``, default ``runs``) to ``parser`` and parse ``argv``; a
    value below ``min_runs`` is a usage error (exit 2)."""
    parser.add_argument("--repeats", type=int, default=runs,
                        help=f"{what}, >= {min_runs} (default {runs})")
    args = parser.parse_args(argv)
    if args.repeats < min_runs:
        parser.error(f"--repeats must be >= {min_runs}")
    return args
