"""Bounded submission: keep at most ``limit`` futures in flight, so a recording of millions
of frames never becomes one graph of millions of tasks."""

from collections.abc import Iterator

from distributed import Future, as_completed


def in_bounded_window(futures: Iterator[Future], limit: int) -> Iterator[Future]:
    """Pull futures from ``futures`` (which submits as it is pulled); yield each once finished."""
    done = as_completed()
    in_flight = 0
    for future in futures:
        done.add(future)
        in_flight += 1
        while in_flight >= limit:
            yield next(done)
            in_flight -= 1
    yield from done


def window_size(client) -> int:
    """A few tasks per worker: enough to keep every worker busy, few enough to stay small."""
    return 4 * max(1, len(client.scheduler_info()["workers"])) + 4
