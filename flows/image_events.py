"""Progress of the measuring tasks image by image, from the Dask workers to the flow.

A measuring task holds many images (72 full-size frames on two threads: a first batch of 36,
~10 s; at 300 frames one of 150, ~50 s), and its result reaches the flow only when the
whole batch is done. So that a person at the terminal sees every image as it is measured,
each task also reports each image through Dask's event log:

- worker side, :func:`report_image`: ``Worker.log_event(TOPIC, {"run", "image", "status", "worker"})``
  after each image (cheap: a message in the worker's batched stream to the scheduler);
- flow side, :class:`ImageCounts`: one subscription per Dask client to :data:`TOPIC`; the
  scheduler forwards the events to it, and a dispatcher hands each one to the counts of its
  run (a random token), so that the fleet's sessions sharing one client, or two commands
  sharing a standing cluster, each count only their own images.

Counting is idempotent (an image counts once, by name): an event that arrives after its
task's result, or never (a worker that died), changes nothing; the task results stay the
record of what was measured. The subscription is never removed (Dask's client raises on
an event whose topic it no longer knows); an event of a finished run is ignored. The
scheduler keeps the last events of a topic in a bounded log
(``distributed.admin.low-level-log-length``), so one topic for all runs keeps its memory
bounded on a cluster that stands for years.
"""

from __future__ import annotations

import secrets
import threading
import weakref
from collections.abc import Callable

__all__ = ["TOPIC", "ImageCounts", "report_image"]

TOPIC = "fieldcal-images"
STATUSES = ("measured", "cached", "bad")

_lock = threading.Lock()
_runs: dict[str, ImageCounts] = {}
_subscribed: weakref.WeakSet = weakref.WeakSet()     # Dask clients with the dispatcher


def report_image(run: str | None, image: str, status: str | None) -> None:
    """Tell the flow of run ``run`` that ``image`` is done (inside a Dask task; never raises).

    Outside a Dask worker (or with ``run`` None) it does nothing."""
    if not run:
        return
    try:
        from distributed import get_worker

        worker = get_worker()
        worker.log_event(TOPIC, {"run": run, "image": str(image), "status": str(status), "worker": worker.address})
    except Exception:  # noqa: BLE001 - progress must never fail a measuring task
        pass


def _dispatch(event) -> None:
    """The client's handler of :data:`TOPIC`: ``event`` is ``(timestamp, msg)``."""
    try:
        msg = event[1]
        with _lock:
            counts = _runs.get(msg["run"])
        if counts is not None:
            counts.add([(msg["image"], msg["status"])])
    except Exception:  # noqa: BLE001 - a malformed event from another program on the cluster
        pass


class ImageCounts:
    """Images done so far in one run's fan-out, from the workers' events and the task results.

    Parameters
    ----------
    total : int
        Images of the fan-out.
    on_change : callable
        ``on_change(done=, cached=, bad=)``, called (under this object's lock, so never twice
        at once) whenever the counts change.
    client : distributed.Client, optional
        The client whose workers report; None: only :meth:`add` counts (no events).
    """

    def __init__(self, total: int, on_change: Callable[..., None], client=None):
        self.total = total
        self.run: str | None = None
        self._on_change = on_change
        self._status: dict[str, str] = {}
        self._lock = threading.Lock()
        self._open = True
        if client is not None:
            self.run = secrets.token_hex(8)
            with _lock:
                _runs[self.run] = self
                if client not in _subscribed:
                    client.subscribe_topic(TOPIC, _dispatch)
                    _subscribed.add(client)

    def counts(self) -> dict[str, int]:
        """``done``, ``cached``, ``bad``: images done, and of them cached and left out."""
        with self._lock:
            return self._counts()

    def _counts(self) -> dict[str, int]:
        values = list(self._status.values())
        return {"done": len(values), "cached": values.count("cached"), "bad": values.count("bad")}

    def add(self, done: list[tuple[str, str | None]]) -> None:
        """Count the ``(image, status)`` pairs as done (an image once: a later report of it
        changes nothing); one ``on_change`` for them all."""
        with self._lock:
            new = [(image, status) for image, status in done if image not in self._status]
            if not self._open or not new:
                return
            for image, status in new:
                self._status[image] = status if status in STATUSES else "measured"
            self._on_change(**self._counts())

    def close(self) -> None:
        """Stop counting (events still on their way are ignored)."""
        with self._lock:
            self._open = False
        with _lock:
            if self.run is not None:
                _runs.pop(self.run, None)
