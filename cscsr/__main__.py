"""``python -m cscsr``: the same command line as ``cscsr``."""

from pipeline.cli import main

if __name__ == "__main__":
    main()
