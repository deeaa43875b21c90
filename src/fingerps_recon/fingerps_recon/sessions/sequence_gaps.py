"""Messages lost before a subscriber took them, from gaps in publication sequence numbers.

The RMW gives each received message the publisher's sequence number
(``publication_sequence_number`` of rclpy's message info; Fast DDS numbers every sample a
writer sends 1, 2, 3, ...). A subscriber that is slower than its publisher loses messages
inside DDS without being told: a reliable keep-last reader's history is overwritten (no
"message lost" event fires for that), a best-effort one simply misses samples. Every
message skipped shows as a jump in the sequence numbers.

rclpy's message info carries no publisher id, so gaps are counted only while a topic has a
single publisher (every fingerps topic has one); with several, their numbers interleave and
nothing is counted. A number at or below the last one (a publisher restarted) starts over.

No rclpy here.
"""

from __future__ import annotations


class SequenceGaps:
    """Counts, per topic, the messages skipped in each publisher's sequence numbers."""

    def __init__(self) -> None:
        self._last: dict[str, int] = {}
        self.lost: dict[str, int] = {}
        """Messages skipped so far, per topic."""

    def observe(self, topic: str, sequence: int | None, publishers: int) -> int:
        """Note a message's publication sequence number; return how many were skipped.

        Parameters
        ----------
        topic : str
            Its topic.
        sequence : int or None
            ``publication_sequence_number`` (None or 0 when the RMW does not give it).
        publishers : int
            Publishers on the topic now.
        """
        if not sequence:
            return 0
        last = self._last.get(topic)
        self._last[topic] = sequence
        if last is None or publishers != 1 or sequence <= last:
            return 0
        skipped = sequence - last - 1
        if skipped:
            self.lost[topic] = self.lost.get(topic, 0) + skipped
        return skipped
