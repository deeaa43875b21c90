"""The zstd level of the MCAP chunks fingerps writes: level 1, the level the MCAP C++ writer
under ``ros2 bag record`` uses by default (``mcap::CompressionLevel::Default``), instead of
level 3, the default of ``zstandard.compress`` that the mcap Python writer calls.

The Python writer (``mcap.writer.Writer``) takes no level: it compresses each chunk by
``zstandard.compress(data)`` of the module it imported as ``mcap.writer.zstandard``.
:func:`use_zstd_level` puts there a stand-in whose ``compress`` is zstandard's at the level
given; everything else the writer does is unchanged. On the rig's session data the two
levels compress equally and level 1 takes half the time (``bench/bench_chunk_compression.py``,
``recorder.zstd_*``), which a recorder beside the reconstruction on two cores needs.
``tests/core/test_session_bag.py`` checks that the chunks written are level 1's.
"""

from __future__ import annotations

import mcap.writer
import zstandard

ZSTD_LEVEL = 1
"""The level of the chunks (MCAP C++'s default, as ``ros2 bag record`` writes them)."""


class LevelledZstd:
    """``zstandard.compress`` at a fixed level (a new compressor per call: the writer may
    be used from more than one thread, and a compressor is not thread-safe)."""

    def __init__(self, level: int) -> None:
        self.level = int(level)

    def compress(self, data: bytes) -> bytes:
        return zstandard.ZstdCompressor(level=self.level).compress(data)


def use_zstd_level(level: int = ZSTD_LEVEL) -> None:
    """Make the mcap writer compress its zstd chunks at ``level``; a no-op if this mcap
    writer does not compress through ``mcap.writer.zstandard`` (it then keeps its own
    level)."""
    if getattr(mcap.writer, "zstandard", None) is not None:
        mcap.writer.zstandard = LevelledZstd(level)  # type: ignore[attr-defined]
