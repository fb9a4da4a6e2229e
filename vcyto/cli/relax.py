"""`vcyto relax`: the relaxation benchmark, an elliptical membrane relaxing in fluid at rest on nested meshes."""

from __future__ import annotations

from ..arguments import Quantity
from ..options import scenario_from, scenario_options
from .common import UsageError, emit, output_options
from .stability import mesh_sizes

DEFAULT_SCENARIO = "examples/scenarios/relaxation.toml"


def add_command(commands):
    relax = commands.add_parser(
        "relax", help="the relaxation benchmark: an ellipse relaxing in fluid at rest on nested meshes, the area "
                      "kept and the relaxation time with their observed orders")
    scenario_options(relax)
    relax.add_argument("--cell", default="ellipse", help="the cell type that relaxes (default ellipse)")
    relax.add_argument("--time", type=Quantity("time", "ms", low=0, low_open=True, high=100.0), default="1.2",
                       metavar="TIME", help="how long it relaxes (ms; default 1.2)")
    relax.add_argument("--mesh-sizes", default="5um,2.5um,1.25um",
                       help="comma-separated mesh sizes; three refined by one ratio give the observed orders "
                            "(default 5um,2.5um,1.25um)")
    output_options(relax)
    relax.set_defaults(handler=command_relax)


def command_relax(args):
    from ..progress import Progress
    from ..studies import relaxation
    if args.scenario is None:
        raise UsageError(f"--scenario: the benchmark needs a scenario with every inlet shut, e.g. {DEFAULT_SCENARIO}")
    scenario = scenario_from(args)
    relaxation.check_at_rest(scenario)
    scenario.cell_type(args.cell)
    sizes = mesh_sizes(args.mesh_sizes, scenario)
    progress = Progress(quiet=args.quiet or args.json)
    try:
        result = relaxation.relaxation(scenario, args.cell, args.time, sizes, progress)
    finally:
        progress.close()
    emit(args, result, relaxation.report_lines(result))
    if result["interrupted"]:
        raise KeyboardInterrupt
