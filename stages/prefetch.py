"""Work made ahead of its consumer, in order, with errors raised where the consumer asks.

The one home for prefetching: ingest reads the next block while it writes this one
(``prefetched``), training makes the next batches while the network steps (``made_ahead``).
Neither may swallow an error: a producer that fails raises in the consumer, never leaves it
waiting."""

import queue
import threading
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor
from typing import TypeVar

T = TypeVar("T")
_DONE = object()


def prefetched(items: Iterator[T], depth: int = 1) -> Iterator[T]:
    """Yield ``items`` in order while a thread produces up to ``depth`` items ahead.

    An exception raised by the producer is re-raised in the consumer at the same point;
    closing the consumer early stops the producer.
    """
    ready: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def produce():
        try:
            for item in items:
                while not stop.is_set():
                    try:
                        ready.put((item, None), timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            ready.put((_DONE, None))
        except BaseException as error:  # handed to the consumer, which raises it
            ready.put((_DONE, error))

    worker = threading.Thread(target=produce, name="prefetch", daemon=True)
    worker.start()
    try:
        while True:
            item, error = ready.get()
            if error is not None:
                raise error
            if item is _DONE:
                return
            yield item
    finally:
        stop.set()
        worker.join(timeout=5)


def made_ahead(make: Callable[[int], T], keys: Iterable[int], workers: Executor, ahead: int) -> Iterator[T]:
    """Yield ``make(key)`` for each key in order, with up to ``ahead`` calls running on ``workers``.

    An exception raised by a call (or a worker process that died) is raised in the consumer when it
    reaches that key; closing the consumer cancels the calls not yet started and does not wait for
    the running ones.
    """
    keys = iter(keys)
    pending: list = []
    try:
        while True:
            while len(pending) < ahead and (key := next(keys, _DONE)) is not _DONE:
                pending.append(workers.submit(make, key))
            if not pending:
                return
            yield pending.pop(0).result()
    finally:
        workers.shutdown(wait=False, cancel_futures=True)
