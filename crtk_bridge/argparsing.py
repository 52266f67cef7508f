"""argparse for the command-line tools (``crtk-bridge``, ``crtk-ctl``): an unknown argument is
named before a missing required option.

argparse checks the required options before it looks at what is left over, so ``crtk-bridge
check --bogus`` said ``the following arguments are required: --profile`` and never named
``--bogus``, the user's actual mistake (a misspelt ``--profil``, say). The standard library and
crtk_bridge.errors only: the client's tools import it too.
"""

from __future__ import annotations

import argparse
import sys

from .errors import CrtkBridgeError


class _Probing(CrtkBridgeError):
    """An error while probing for unknown arguments: the original message stands."""


class ArgumentParser(argparse.ArgumentParser):
    """An ``argparse.ArgumentParser`` whose "the following arguments are required" error names
    the unrecognized arguments instead, when there are any."""

    _argv: list[str] | None = None
    _probing = False

    def parse_known_args(self, args=None, namespace=None):
        self._argv = list(sys.argv[1:] if args is None else args)
        return super().parse_known_args(self._argv, namespace)

    def unknown_first(self, message: str) -> str:
        """``message``, or ``unrecognized arguments: ...`` when it says a required option is
        missing and the arguments hold some this parser does not know."""
        if self._probing or self._argv is None or not message.startswith("the following arguments are required"):
            return message
        required = [a for a in self._actions if a.required]  # options and positionals
        for a in required:
            a.required = False
        self._probing = True
        try:
            _, extras = argparse.ArgumentParser.parse_known_args(self, list(self._argv), None)
        except (_Probing, SystemExit):
            return message
        finally:
            self._probing = False
            for a in required:
                a.required = True
        return f"unrecognized arguments: {' '.join(extras)}" if extras else message

    def error(self, message: str):
        if self._probing:
            raise _Probing(message)
        super().error(self.unknown_first(message))
