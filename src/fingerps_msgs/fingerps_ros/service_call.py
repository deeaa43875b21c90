"""A service call from a thread other than the one spinning the caller's node (an action's
execute callback, a service callback in a reentrant group, a command's main thread), waited
for with a timeout."""

from __future__ import annotations

import threading
from typing import Any

from rclpy.client import Client


def call_service(client: Client, request: object, timeout_s: float) -> Any | None:
    """Call ``client``'s service with ``request`` and wait up to ``timeout_s`` for the answer:
    the response, or None when none came in time (the pending request is then forgotten,
    so a late answer is dropped). The caller says what the missing answer means."""
    done = threading.Event()
    future = client.call_async(request)
    future.add_done_callback(lambda _future: done.set())
    if not done.wait(timeout_s):
        client.remove_pending_request(future)
        return None
    return future.result()
