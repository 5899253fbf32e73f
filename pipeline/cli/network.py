"""Commands on the network, its weights and the test set: model-info, train, export-weights, make-testset, evaluate-testset."""

import contextlib
import dataclasses
import os
import re
from typing import Annotated, Optional

import typer

from rich.table import Table
from pipeline.cli.core import Scheduler, Workers, command, command_line, counted, show_table, stdout


@command("model-info")
def model_info(config: Annotated[str, typer.Option(help="Named configuration: lite, full or lite-mono (mono recordings).")] = "lite",
               weights: Annotated[Optional[str], typer.Option(help="Describe this weights file instead.")] = None):
    """Parameter counts and settings of a CSCSR network configuration (or of a weights file)."""
    from cscsr.weights.model_info import model_info as describe

    rows = describe(config, weights)
    show_table(f"CSCSR {rows['configuration']}", rows)


@command()
def train(context: typer.Context,
          out: Annotated[str, typer.Argument(help="Folder for checkpoints, log.jsonl and the final weights.")],
          config: Annotated[str, typer.Option(help="Network configuration: lite, full or lite-mono (mono clips; --init a colour file "
                                                       "starts it from that file's green branch).")] = "lite",
          steps: Annotated[int, typer.Option(help="Optimiser steps in all (a resumed run continues to this).")] = 20000,
          batch: Annotated[int, typer.Option(help="Clips per step.")] = 8,
          lr_side: Annotated[int, typer.Option(help="LR crop side of a training clip (even).")] = 32,
          learning_rate: Annotated[float, typer.Option(help="Adam learning rate (after the warm-up, x0.9 every "
                                                             "--decay-every steps).")] = 2e-4,
          warmup: Annotated[int, typer.Option(help="Steps of linear learning-rate warm-up.")] = 200,
          decay_every: Annotated[int, typer.Option(help="Steps between x0.9 learning-rate decays; may change on "
                                                        "--resume (the rate drops at once to its new place on the "
                                                        "schedule: an annealing phase).")] = 7500,
          seed: Annotated[int, typer.Option(help="Seed of the clips and the initial weights.")] = 0,
          pool: Annotated[int, typer.Option(help="Clips simulated up front and reused under 8 flips and turns "
                                                 "(0: a fresh clip every time); may grow on --resume.")] = 0,
          init: Annotated[Optional[str], typer.Option(help="Start from the weights in this file instead of random ones "
                                                           "(fine-tuning, e.g. on larger --lr-side crops).")] = None,
          motion: Annotated[str, typer.Option(help="Ablation: joint or assembled motion estimation.")] = "joint",
          flow_guidance: Annotated[bool, typer.Option("--flow-guidance/--no-flow-guidance",
                                                      help="Ablation: fuse time points aligned by flow, or not.")] = True,
          checkpoint_every: Annotated[int, typer.Option(help="Steps between checkpoints.")] = 100,
          validate_every: Annotated[int, typer.Option(help="Steps between validation PSNR lines.")] = 250,
          validation_clips: Annotated[int, typer.Option(help="Held-out clips each validation averages (fixed: "
                                                            "dead leaves, alpha 0.6 to 1.0).")] = 8,
          pictures: Annotated[Optional[list[str]], typer.Option(
              help="A folder of training pictures (repeat for more; default: the bundled pictures).")] = None,
          dead_leaves: Annotated[float, typer.Option(help="Share of clips showing dead leaves.")] = 0.4,
          device: Annotated[str, typer.Option(help="cpu or cuda (cuda: clips synthesised on the GPU).")] = "cpu",
          precision: Annotated[str, typer.Option(help="fp32 or bf16 (autocast).")] = "fp32",
          synthesis: Annotated[str, typer.Option(help="Clips by numpy or torch (on the device; the same clips); "
                                                      "auto: torch on a GPU.")] = "auto",
          time_budget: Annotated[float, typer.Option(help="Stop cleanly, checkpointed, before this many seconds "
                                                          "(0: no limit); --resume continues.")] = 0.0,
          threads: Annotated[Optional[int], typer.Option(help="Torch threads (default: every core).")] = None,
          channels_last: Annotated[bool, typer.Option("--channels-last", help="Convolutions on NHWC tensors (the "
                                                      "same training within rounding; may change on --resume).")] = False,
          resume: Annotated[bool, typer.Option("--resume", help="Continue from OUT/checkpoint.safetensors (to float "
                                                       "rounding), "
                                                       "or from the parts of a portable checkpoint in OUT.")] = False):
    """Train the CSCSR network on clips simulated on the fly; resumable."""
    import torch

    from cscsr.training.train import TrainOptions, train as run
    from pipeline.stores.storage import check_apart
    from stages.numbers import check_number

    check_apart(out, init, *(pictures or []))
    if threads is not None:  # 0 was taken as "every core", -3 failed in torch
        check_number("--threads", threads, at_least=1, integer=True)
        torch.set_num_threads(threads)
    options = TrainOptions(config=config, steps=steps, batch=batch, lr_side=lr_side, learning_rate=learning_rate,
                           warmup=warmup, decay_every=decay_every, seed=seed, pool=pool, init=init or "",
                           motion=motion, flow_guidance=flow_guidance, pictures=os.pathsep.join(pictures or []),
                           dead_leaves=dead_leaves, device=device, precision=precision, time_budget=time_budget,
                           synthesis=synthesis, channels_last=channels_last,
                           checkpoint_every=checkpoint_every, validate_every=validate_every,
                           validation_clips=validation_clips)
    with option_words(TrainOptions):  # "lr_side must be even" -> "--lr-side must be even"
        options.check()
    final = run(options, out, resume=resume, log=lambda line: stdout.print(line, highlight=False),
                command=command_line(context))
    stdout.print(f"weights: {final}")


@contextlib.contextmanager
def option_words(options_class):
    """An error of ``options_class.check()`` that begins with a field's name (the Python API's words) said as the
    command's option: ``lr_side must be even`` -> ``--lr-side must be even``."""
    from stages.errors import InputError

    try:
        yield
    except InputError as error:
        fields = "|".join(field.name for field in dataclasses.fields(options_class))
        said = re.sub(rf"^({fields})\b", lambda match: "--" + match.group(1).replace("_", "-"), str(error))
        raise type(error)(said) from None


@command("export-weights")
def export_weights(folder: Annotated[str, typer.Argument(help="A cscsr train folder.")],
                   dest: Annotated[str, typer.Argument(help="Weights file to write (.safetensors).")],
                   half: Annotated[bool, typer.Option("--half", help="Store float16 (half the size).")] = False,
                   portable: Annotated[bool, typer.Option(
                       "--portable", help="Write DEST as a folder holding the whole checkpoint in parts of at most "
                                          "16 MiB (bf16 Adam moments; fp16 weights with --half), which train "
                                          "--resume continues on another machine (close, not bit-exact).")] = False,
                   overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace DEST if it is a weights file "
                                                           "(--portable: the parts in DEST).")] = False):
    """The latest checkpoint of a training run as a weights file for --weights (or, --portable, as a
    checkpoint small enough to carry to another machine)."""
    from cscsr.training.train import export_portable, export_weights as run
    from pipeline.stores.storage import check_apart

    check_apart(dest, os.path.join(folder, "checkpoint.safetensors"))  # the file it reads (DEST may sit beside it)
    if portable:
        step, parts = export_portable(folder, dest, weights="float16" if half else "float32", overwrite=overwrite)
        stdout.print(f"{dest}: the checkpoint after {counted(step, 'step')} in {counted(len(parts), 'part')}")
        return
    step = run(folder, dest, storage="float16" if half else "float32", overwrite=overwrite)
    stdout.print(f"{dest}: weights after {step} steps")


@command("make-testset")
def make_testset(out: Annotated[str, typer.Argument(help="Folder for the test set (sources, stores, manifest).")],
                 workers: Workers = None,
                 overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace OUT if it exists.")] = False):
    """Simulate the held-out test set (3 pictures x alpha 0.6/0.8/1.0), bit-identically every time."""
    from pipeline.jobs.testset import make_testset as run

    stores = run(out, workers=workers, overwrite=overwrite)
    stdout.print(f"{out}: {len(stores)} spike stores with ground truth")


@command("evaluate-testset")
def evaluate_testset(testset: Annotated[str, typer.Argument(help="A folder made by cscsr make-testset.")],
                     methods: Annotated[str, typer.Option(help="Comma-separated methods.")] = "tfp,tfi",
                     weights: Annotated[Optional[str], typer.Option(help="Network weights for cscsr.")] = None,
                     out: Annotated[str, typer.Option(help="Folder for results.")] = "evaluation-testset",
                     workers: Workers = None, scheduler: Scheduler = None,
                     overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace the --out folder if it is an "
                                                             "evaluation.")] = False):
    """PSNR / SSIM per method and alpha on the test set: table, summary.csv, crops.png."""
    from pipeline.jobs.testset import evaluate_testset as run

    rows = run(testset, [m.strip() for m in methods.split(",") if m.strip()], out, weights=weights, workers=workers,
               scheduler=scheduler, overwrite=overwrite)
    table = Table(title=f"{testset}: x4, mean over pictures and truth frames")
    for column in ("method", "alpha", "PSNR dB", "SSIM", "s / image"):
        table.add_column(column)
    for r in rows:
        table.add_row(r["method"], str(r["alpha"]), f"{r['psnr']:.2f}", f"{r['ssim']:.4f}", f"{r['seconds_per_image']:.3f}")
    stdout.print(table)
