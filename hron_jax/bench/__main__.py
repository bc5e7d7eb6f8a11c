"""`python -m hron_jax.bench <subcommand> [options]`: the one CLI of the benchmarks (hron_jax.bench)."""

from __future__ import annotations

import argparse
import sys

from . import __doc__ as _PACKAGE_DOC
from . import compile, conv, discovery, env, geodesic, graph, model, profile, train
from .common import machine_info, print_load

SUBCOMMANDS = {
    m.__name__.rsplit(".", 1)[1]: m
    for m in (env, graph, model, train, profile, compile, conv, geodesic, discovery)
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m hron_jax.bench",
        description=_PACKAGE_DOC,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="cmd", required=True)
    for name, mod in SUBCOMMANDS.items():
        mod.add_args(
            sub.add_parser(
                name,
                help=mod.__doc__.split(" (`")[0],
                description=mod.__doc__,
                formatter_class=argparse.RawDescriptionHelpFormatter,
            )
        )
    return parser


def main(argv=None) -> None:
    a = build_parser().parse_args(argv)
    if hasattr(SUBCOMMANDS[a.cmd], "before_jax"):  # settings that must precede JAX's backends
        SUBCOMMANDS[a.cmd].before_jax(a)
    from ..cli import tune_malloc

    tune_malloc()
    sys.stdout.reconfigure(line_buffering=True)  # every line out at once: a run stopped early keeps it
    print(machine_info())
    SUBCOMMANDS[a.cmd].run(a)
    print_load()


if __name__ == "__main__":
    main()
