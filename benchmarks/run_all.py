"""Run every benchmark in ``benchmarks/`` in turn (``make bench``).

Each ``benchmarks/*.py`` other than this one and helpers (names starting with ``_``) runs
in its own subprocess with this interpreter, at its default settings (the GPU scripts only
where torch sees a GPU); its output passes
straight through, so each prints its own markdown table and writes its JSON under
``benchmarks/results/``. Exits non-zero if any benchmark failed to run.
"""

import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
GPU_ONLY = {"gpu_lease.py", "gpu_pipeline.py", "gpu_prove.py"}  # run on a lent GPU (docs/gpu.md), skipped where there is none


def main() -> int:
    import torch

    scripts = sorted(p for p in HERE.glob("*.py") if p.name != Path(__file__).name and not p.name.startswith("_"))
    failed = []
    for script in scripts:
        if script.name in GPU_ONLY and not torch.cuda.is_available():
            print(f"\n# {script.name}: skipped (needs a GPU; see docs/gpu.md)\n", flush=True)
            continue
        if script.name == "gpu_lease.py":
            continue  # a sequence of lease commands, not a benchmark to run at its defaults
        print(f"\n# {script.name}\n", flush=True)
        if subprocess.run([sys.executable, str(script)], cwd=HERE.parent).returncode:
            failed.append(script.name)
    if failed:
        print(f"\nfailed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
