"""What a simulation job will do, as frozen data: its steps, in the order they are submitted.

Per time chunk of the output, a :class:`SpikeChunk` (its latent frames' increments, fired on
from the previous chunk's integrator state, written as one chunk of ``spikes``), then a
:class:`TruthFrame` for each ground-truth frame inside the chunk and, under synthetic camera
motion, the :class:`FlowField` from it to the next. Nothing here touches a cluster or a store:
``pipeline.jobs.simulate`` turns each step into tasks and runs them (``pipeline.compute.executor``). The
steps are generated as consumed, so a long recording never exists as one list.
"""

from collections.abc import Iterator
from dataclasses import dataclass

from stages.simulation.latent import bracket, source_position


@dataclass(frozen=True)
class SpikeChunk:
    frames: range  # spike frames start:stop, one chunk of ``spikes``
    source_frames: tuple[int, ...]  # a video's frames i whose pair (i, i + 1) the latent frames lie between


@dataclass(frozen=True)
class TruthFrame:
    index: int  # k: the row of ``truth``
    frame: int  # the spike frame it shows
    source_frame: int | None  # a video's frame i whose pair (i, i + 1) it lies between; None for a still


@dataclass(frozen=True)
class FlowField:
    index: int  # k: the row of ``flow``, from truth frame k to k + 1
    frame0: int
    frame1: int


Step = SpikeChunk | TruthFrame | FlowField


def simulation_steps(n_frames: int, chunk: int, truth_at: list[int], source_frames: int | None,
                     camera_moves: bool) -> Iterator[Step]:
    """The steps of a simulation of ``n_frames`` spike frames in chunks of ``chunk``, with truth at
    ``truth_at``; ``source_frames``: a video's frame count (None for a still); ``camera_moves``:
    a still on a camera path, whose exact flow is stored too."""

    def pair_of(frame: int) -> int:
        return bracket(source_position(frame, n_frames, source_frames), source_frames)[0]

    for start in range(0, n_frames, chunk):
        frames = range(start, min(start + chunk, n_frames))
        pairs = () if source_frames is None else tuple(sorted({pair_of(t) for t in frames}))
        yield SpikeChunk(frames, pairs)
        for k, frame in enumerate(truth_at):
            if frame not in frames:
                continue
            yield TruthFrame(k, frame, None if source_frames is None else pair_of(frame))
            if camera_moves and k + 1 < len(truth_at):
                yield FlowField(k, frame, truth_at[k + 1])
