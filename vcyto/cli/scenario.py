"""`vcyto scenario`: the effective scenario (defaults + file + overrides) as TOML."""

from __future__ import annotations

from ..options import scenario_from, scenario_options


def add_command(commands):
    scenario = commands.add_parser("scenario",
                                   help="print the effective scenario (defaults + file + overrides) as TOML")
    scenario_options(scenario)
    scenario.set_defaults(handler=command_scenario)


def command_scenario(args):
    from ..config import scenario_to_toml
    print(scenario_to_toml(scenario_from(args)), end="")
