"""The user-facing jobs behind `geoavatar <command>`: one module per command, each a typed function."""

from __future__ import annotations

from typing import Any, Callable, Sequence


def call_command(command: Callable[..., Any], argv: Sequence[str], prog: str) -> Any:
    """Run a command function on its command-line words and return what it returns: through its own parser when it
    has one (`command.parse_argv`: train's defaults follow --preset), else tyro on its signature (the docstring is
    the description). A usage error is tyro's SystemExit; a GeoAvatarError goes through to the caller."""
    parse_argv = getattr(command, "parse_argv", None)
    if parse_argv is not None:
        return command(parse_argv(list(argv), prog))
    import tyro

    return tyro.cli(command, args=list(argv), prog=prog)


__all__ = ["call_command"]
