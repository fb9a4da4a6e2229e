"""`vcyto cache [clear]`: the disk cache of set-up results (steady flows, solver couplings, constant matrices,
unit memo)."""

from __future__ import annotations

from .common import emit


def add_command(commands):
    cache = commands.add_parser("cache", help="the disk cache of set-up results (steady flows, solver couplings, "
                                "constant matrices, unit memo): where it is, its size; 'clear' empties it")
    cache.add_argument("action", nargs="?", choices=("info", "clear"), default="info",
                       help="info (default): directory and size; clear: delete every entry")
    cache.add_argument("--json", action="store_true", help="print the result as JSON")
    cache.add_argument("--quiet", action="store_true", help="accepted as by every command (cache prints no progress)")
    cache.set_defaults(handler=command_cache)


def command_cache(args):
    """`vcyto cache [clear]`: where the set-up cache is and what it holds; `clear` empties it."""
    from ..cache import clear, usage
    removed = clear() if args.action == "clear" else None
    result = usage()
    if removed is not None:
        result["removed"] = removed
    lines = [f"set-up cache: {result['directory']} ({'on' if result['enabled'] else 'off: VCYTO_CACHE=off'}), "
             f"{result['entries']} entries, {result['bytes'] / 1e6:.1f} MB"]
    if result["enabled"] and not result["writable"]:
        lines.append("  it cannot be written: every run pays its set-up; set VCYTO_CACHE_DIR to a writable "
                     "directory (or VCYTO_CACHE=off)")
    if removed is not None:
        lines.append(f"removed {removed} files")
    emit(args, result, lines)
