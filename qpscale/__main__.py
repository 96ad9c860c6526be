"""``python -m qpscale``: the command line (:mod:`qpscale.cli`)."""

from .cli import main

if __name__ == "__main__":
    main()
