"""recon_node's ``/diagnostics`` status, built from the worker's bookkeeping (no node)."""

from __future__ import annotations

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus

from fingerps_recon.photometric.kernel_threads import available_cores, thread_limit
from fingerps_recon.reconstruction.worker import ReconstructionWorker
from fingerps_ros.diagnostics import key_values


def reconstruction_status(name: str, worker: ReconstructionWorker, *,
                          compressed_failures: int) -> DiagnosticStatus:
    """The status ``<name>: reconstruction``: the worker's health level and message, its
    counters, the fingerprint's, the compressed companions' failures and the median of each
    stage of the recent bursts (``StageTimes``)."""
    w = worker
    status = DiagnosticStatus(name=f"{name}: reconstruction")
    status.level, status.message = w.health()
    values = {"ready": str(w.ready), "threads": str(thread_limit()),
              "cores": str(available_cores()), "bursts_done": str(w.done),
              "bursts_failed": str(w.failed), "bursts_incomplete": str(w.incomplete),
              "bursts_rejected": str(w.rejected), "unexpected_errors": str(w.unexpected),
              "calibrations_refused": str(w.calibration.refused_count),
              "bursts_without_flat_field": str(w.flat_unused), "last_error": w.last_error,
              "last_problem": w.last_problem, "fingerprints_made": str(w.prints_made),
              "fingerprints_rejected": str(w.prints_rejected),
              "last_fingerprint_problem": w.last_print_problem,
              "fingerprint_ms_median": (f"{float(np.median(w.print_ms)):.1f}" if w.print_ms
                                        else ""),
              "bursts_dropped": str(w.dropped), "compressed_failures": str(compressed_failures),
              "calibrated": str(w.calibration.lights is not None),
              "calibrations_prepared": str(w.calibration.prepared.count),
              **{key: f"{value:.1f}" for key, value in w.stages.medians().items()}}
    status.values = key_values(values)
    return status
