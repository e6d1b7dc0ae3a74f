"""Run the benchmarks: ``python -m tests.bench [NAME ...]``."""

from __future__ import annotations

import importlib
import pkgutil
import sys

import tests.bench as package
from cli.pages import numpy_page_advice


def main(argv: list[str]) -> int:
    numpy_page_advice()  # as the tbp command does; the benchmarks' own subprocesses inherit it
    names = sorted(m.name for m in pkgutil.iter_modules(package.__path__) if not m.name.startswith("_"))
    chosen = argv or names
    unknown = sorted(set(chosen) - set(names))
    if unknown:
        print(f"unknown benchmark {unknown[0]!r}; available: {', '.join(names)}", file=sys.stderr)
        return 2
    for name in chosen:
        module = importlib.import_module(f"tests.bench.{name}")
        print(f"== {name}", flush=True)
        module.run()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
