"""Run every benchmark in ``benchmarks/`` in turn (``make bench``).

Each ``benchmarks/*.py`` other than this one and helpers (names starting with ``_``) runs
in its own subprocess with this interpreter, at its default settings; its output passes
straight through, so each prints its own markdown table and writes its JSON under
``benchmarks/results/``. Exits non-zero if any benchmark failed to run.
"""

import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main() -> int:
    scripts = sorted(p for p in HERE.glob("*.py") if p.name != Path(__file__).name and not p.name.startswith("_"))
    failed = []
    for script in scripts:
        print(f"\n# {script.name}\n", flush=True)
        if subprocess.run([sys.executable, str(script)], cwd=HERE.parent).returncode:
            failed.append(script.name)
    if failed:
        print(f"\nfailed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
