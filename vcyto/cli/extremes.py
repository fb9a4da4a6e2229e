"""`vcyto extremes`: the FE-IB plant at extreme settings; each case runs correctly or stops with a specific
diagnosis."""

from __future__ import annotations

from ..options import scenario_from, scenario_options
from .common import UsageError, emit, output_options


def add_command(commands):
    extremes = commands.add_parser("extremes", help="the FE-IB plant at extreme settings: each case runs correctly "
                                                    "or stops with a specific diagnosis")
    scenario_options(extremes)
    extremes.add_argument("--fast", action="store_true", help="the test suite's variants: coarse meshes, short runs")
    extremes.add_argument("--case", metavar="NAMES", help="only these cases, e.g. a1,c2 (default: all)")
    output_options(extremes)
    extremes.set_defaults(handler=command_extremes)


def command_extremes(args):
    from ..progress import Progress
    from ..studies import extremes
    base = scenario_from(args)
    names = [name.strip() for name in args.case.split(",") if name.strip()] if args.case is not None else None
    known = [case.name for case in extremes.CASES]
    unknown = [name for name in names or () if name not in known]
    if unknown or names == []:
        raise UsageError(f"--case: unknown case {', '.join(unknown) or repr(args.case)}; known: {', '.join(known)}")
    progress = Progress(quiet=args.quiet or args.json)
    try:
        result = extremes.run_cases(base, fast=args.fast, names=names, progress=progress)
    finally:
        progress.close()
    emit(args, result, extremes.report_lines(result))
    if result["interrupted"]:
        raise KeyboardInterrupt         # the finished cases are printed; the exit is an interrupt's (130)
    if not result["passed"]:
        raise extremes.UnexpectedOutcome(f"{sum(not row['passed'] for row in result['rows'])} case(s) did not "
                                         "end as expected (see the table)")
