"""How every fingerps command-line tool starts and ends: private files, parsing, one error
line, the exit code.

The tools (calibrate_camera, calibrate_lights, offline_recon, offline_tune, bag_recover,
bringup, the demo) run their job through :meth:`CommandLineTool.main`:

1. the owner-only umask (:func:`fingerps_ros.privacy.start_private_tool`; a bad
   ``FINGERPS_UMASK`` is one line on stderr and exit code 2);
2. the arguments (argparse: a bad option prints the usage and exits 2 itself);
3. the job, which returns the exit code; an exception of the tool's bad-input types becomes
   one line ``<prog>: error: <message>`` on stderr and exit code 2, one of its failure types
   the same line (after an optional context) and exit code 1. Other exceptions are bugs and
   keep their traceback.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from fingerps_ros.errors import FingerpsError
from fingerps_ros.privacy import start_private_tool

EXIT_FAILED = 1
"""The job ran on good input and did not succeed (a calibration failed its checks, the
outputs could not be written)."""
EXIT_BAD_INPUT = 2
"""The input is wrong; the one line on stderr says what to fix (a node started with a bad
parameter exits with it too: ``node_runner``)."""

ErrorTypes = tuple[type[BaseException], ...]


@dataclass(frozen=True)
class CommandLineTool:
    """One tool's name and which exceptions mean bad input and which a failed job.

    Attributes
    ----------
    prog : str
        The executable's name, first on every error line.
    bad_input : tuple of exception types
        Exit code 2 with ``<prefix><message>``.
    failed : tuple of exception types
        Exit code 1 with ``<prefix><failed_context><message>``; checked after ``bad_input``.
    failed_context : str
        Said before a failure's message, e.g. ``"cannot write the outputs: "``.
    error_prefix : str or None
        What starts an error line; None for ``"<prog>: error: "``.
    """

    prog: str
    bad_input: ErrorTypes = (FingerpsError,)
    failed: ErrorTypes = ()
    failed_context: str = ""
    error_prefix: str | None = None

    def main(self, parser: argparse.ArgumentParser,
             job: Callable[[argparse.Namespace], int],
             argv: Sequence[str] | None = None) -> int:
        """Set the private umask, parse ``argv``, run ``job``; return the exit code."""
        if not start_private_tool(self.prog):  # owner-only files (fingerps_ros.privacy)
            return EXIT_BAD_INPUT
        args = parser.parse_args(argv)
        try:
            return job(args)
        except self.bad_input as exc:
            self.error(exc)
            return EXIT_BAD_INPUT
        except self.failed as exc:
            self.error(f"{self.failed_context}{exc}")
            return EXIT_FAILED

    def error(self, message: object) -> None:
        """Print one error line on stderr."""
        prefix = f"{self.prog}: error: " if self.error_prefix is None else self.error_prefix
        print(f"{prefix}{message}", file=sys.stderr, flush=True)


def positive_number(text: str) -> float:
    """An argparse ``type``: a number > 0 (else the option's error names the fix)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"{text} must be > 0")
    return value
