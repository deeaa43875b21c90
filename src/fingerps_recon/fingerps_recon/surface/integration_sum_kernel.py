"""The float64 sum of the integration's compiled passes: eight partial sums, in a fixed order.

IEEE arithmetic forbids LLVM to reorder a sum (:mod:`photometric.kernel_compile`), so a sum
over pixels is one chain of dependent additions unless it is split by hand:
:func:`ordered_sum` keeps eight independent chains and adds them at the end, the same way on
every machine. The kernels that sum longer runs keep their sums per column instead
(element-wise, vectorised) and add the columns up with it. Inlined into its callers;
importing this module needs numba.
"""

from __future__ import annotations

from fingerps_recon.photometric.kernel_compile import drop_stale_caches, inline_kernel


@inline_kernel
def ordered_sum(values, start, stop):
    """sum(values[start:stop]) in float64, eight partial sums (independent chains)."""
    s0 = s1 = s2 = s3 = s4 = s5 = s6 = s7 = 0.0
    c = start
    while c + 8 <= stop:
        s0 += values[c]
        s1 += values[c + 1]
        s2 += values[c + 2]
        s3 += values[c + 3]
        s4 += values[c + 4]
        s5 += values[c + 5]
        s6 += values[c + 6]
        s7 += values[c + 7]
        c += 8
    while c < stop:
        s0 += values[c]
        c += 1
    return ((s0 + s1) + (s2 + s3)) + ((s4 + s5) + (s6 + s7))


# After an edit of the compile options, the cached kernels are compiled anew.
drop_stale_caches(globals())
