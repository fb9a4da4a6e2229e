"""`vcyto stability`: the largest stable dt per cell type and mesh size."""

from __future__ import annotations

from .. import arguments as limits
from .. import units
from ..options import scenario_from, scenario_options
from .common import UsageError, emit, output_options


def add_command(commands):
    stability = commands.add_parser("stability", help="measure the largest stable dt per cell type and mesh size")
    scenario_options(stability)
    stability.add_argument("--cells", default="RBC,melanoma", help="cell types (default RBC,melanoma)")
    stability.add_argument("--mesh-sizes", default="6.667um,3.333um,1.667um",
                           help="comma-separated mesh sizes (default 6.667um,3.333um,1.667um)")
    output_options(stability)
    stability.set_defaults(handler=command_stability)


def _lengths(text: str) -> list[float]:
    values = units.parse_list(text, "length", field="--mesh-sizes")
    if not values or any(v <= 0 for v in values):
        raise UsageError(f"--mesh-sizes: needs positive lengths such as 6.67um,3.33um (got {text!r})")
    return values


def mesh_sizes(text: str, scenario) -> list[float]:
    """The lengths of ``--mesh-sizes``, each checked to resolve the scenario's inlets and to fit in memory."""
    sizes = _lengths(text)
    for h in sizes:
        scenario.with_numerics(mesh_h=h)          # validates that each mesh resolves the inlets
        limits.check_mesh(scenario.channel.length, scenario.channel.height, h, "--mesh-sizes")
    return sizes


def command_stability(args):
    from ..progress import Progress
    from ..studies import stabilitymap
    scenario = scenario_from(args)
    cells = [name.strip() for name in args.cells.split(",") if name.strip()]
    if not cells:
        raise UsageError("--cells: needs at least one cell type, e.g. --cells RBC,melanoma")
    for name in cells:
        scenario.cell_type(name)
    sizes = mesh_sizes(args.mesh_sizes, scenario)
    progress = Progress(quiet=args.quiet or args.json)
    try:
        result = stabilitymap.stability_map(scenario, cells, sizes, progress)
    finally:
        progress.close()
    emit(args, result, stabilitymap.report_lines(result))
    if result["interrupted"]:
        raise KeyboardInterrupt         # the rows finished are printed; the exit is an interrupt's (130)
