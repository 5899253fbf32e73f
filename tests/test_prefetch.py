"""Work made ahead of its consumer (stages.prefetch): order, a bounded lead, and errors that reach
the consumer instead of leaving it waiting (training once hung forever on a batch that failed)."""

import threading
from concurrent.futures import ThreadPoolExecutor

from stages.prefetch import made_ahead


def _consume(items, seen: list, outcome: dict) -> threading.Thread:
    """Drain ``items`` in a thread, so a consumer that would wait forever fails the test instead."""
    def drain():
        try:
            for item in items:
                seen.append(item)
            outcome["error"] = None
        except Exception as error:  # noqa: BLE001 - the test inspects it
            outcome["error"] = error

    thread = threading.Thread(target=drain, daemon=True)
    thread.start()
    thread.join(timeout=60)
    assert not thread.is_alive(), "the consumer is still waiting"
    return thread


def test_made_ahead_keeps_order_and_a_bounded_lead():
    started, taken = [], []
    lead = []

    def make(key):
        started.append(key)
        return key * key

    for value in made_ahead(make, range(1, 31), ThreadPoolExecutor(3), ahead=4):
        taken.append(value)
        lead.append(len(started) - len(taken))
    assert taken == [k * k for k in range(1, 31)]
    assert max(lead) <= 3  # at most `ahead` calls beyond the ones consumed, the one in hand included


def test_a_failed_call_is_raised_in_the_consumer_at_its_key():
    def make(key):
        if key == 3:
            raise ValueError("bad batch 3")
        return key

    seen, outcome = [], {}
    _consume(made_ahead(make, range(1, 10), ThreadPoolExecutor(2), ahead=2), seen, outcome)
    assert seen == [1, 2] and isinstance(outcome["error"], ValueError)


def test_training_batches_raise_a_failed_batch_instead_of_hanging(monkeypatch):
    from cscsr.training import training_batches

    def make_batch(step, *args, **kwargs):
        if step == 3:
            raise RuntimeError("could not read picture 7")
        return step

    monkeypatch.setattr(training_batches, "make_batch", make_batch)
    seen, outcome = [], {}
    _consume(training_batches._prefetch(0, training_batches.TrainOptions(steps=10)), seen, outcome)
    assert seen == [1, 2]
    assert isinstance(outcome["error"], RuntimeError) and "picture 7" in str(outcome["error"])


def test_closing_early_cancels_what_has_not_started():
    started = []
    gate = threading.Event()

    def make(key):
        started.append(key)
        gate.wait(5)
        return key

    workers = ThreadPoolExecutor(1)
    items = made_ahead(make, range(1, 100), workers, ahead=5)
    gate.set()
    assert next(items) == 1
    items.close()
    workers.shutdown(wait=True)
    assert len(started) <= 6  # the queued calls were cancelled, not run to the end of the range
