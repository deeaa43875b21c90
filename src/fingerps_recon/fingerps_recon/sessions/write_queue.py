"""The recorder's queue between intake and the bag writer: bounded in bytes, drops the oldest.

No rclpy here.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass


@dataclass
class PendingMessage:
    """A serialized message waiting to be written."""

    topic: str
    data: bytes
    log_time_ns: int
    publish_time_ns: int


class WriteQueue:
    """FIFO of messages bounded in bytes; full, it drops the oldest message (counted)."""

    def __init__(self, limit_bytes: int) -> None:
        self._limit = limit_bytes
        self._items: deque[PendingMessage] = deque()
        self._bytes = 0
        self._closed = False
        self._cv = threading.Condition()
        self.dropped: dict[str, int] = {}
        """Messages dropped to make room, per topic."""

    def put(self, item: PendingMessage) -> int:
        """Append; return how many old messages were dropped to make room."""
        dropped = 0
        with self._cv:
            while self._items and self._bytes + len(item.data) > self._limit:
                old = self._items.popleft()
                self._bytes -= len(old.data)
                self.dropped[old.topic] = self.dropped.get(old.topic, 0) + 1
                dropped += 1
            self._items.append(item)
            self._bytes += len(item.data)
            self._cv.notify()
        return dropped

    def take_all(self, timeout: float) -> tuple[list[PendingMessage], bool]:
        """Wait up to ``timeout`` s for messages; return them all and whether closed."""
        with self._cv:
            if not self._items and not self._closed:
                self._cv.wait(timeout=timeout)
            items = list(self._items)
            self._items.clear()
            self._bytes = 0
            return items, self._closed

    def close(self) -> None:
        """Let the consumer finish once the queue is empty."""
        with self._cv:
            self._closed = True
            self._cv.notify_all()
