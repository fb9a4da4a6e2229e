"""`vcyto scenario`: the effective scenario (defaults + file + overrides) as TOML, or with --json as JSON."""

from __future__ import annotations

from ..options import scenario_from, scenario_options
from ..outputs import strict_json
from .common import output_options


def add_command(commands):
    scenario = commands.add_parser("scenario",
                                   help="print the effective scenario (defaults + file + overrides) as TOML "
                                        "(--json: the same tree as JSON)")
    scenario_options(scenario)
    output_options(scenario)
    scenario.set_defaults(handler=command_scenario)


def command_scenario(args):
    from ..config import scenario_to_toml, tomllib
    text = scenario_to_toml(scenario_from(args))
    if args.json:                       # the TOML's tree, read back as a scenario file is read: same keys, SI
        print(strict_json(tomllib.loads(text)))
    else:
        print(text, end="")
