"""The command line's argument parser: a subcommand's own usage on a bad option, a suggestion
for a misspelt one, and negative values read as values.

Plain argparse hands a subcommand's unknown options up to ``flowrt`` itself, which prints the
top-level usage (``flowrt run --duraton 3`` showed how to call ``flowrt``, not ``run``), and
reads ``--split-duration -3s`` as two options (``expected one argument``) because ``-3s`` is
not a number to it. Here the subcommand that was given the option refuses it, with its usage
and ``did you mean --duration?``, and a value that starts with ``-`` and a digit is the value
of the option before it, so the option's own check says ``must be more than 0``. A command
group given no command (``flowrt ctl``) says so in one line, with the commands it takes, not
argparse's ``the following arguments are required: ctl_command``.
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Sequence
from typing import NoReturn

from ..graph.diagnostics import closest

_NEGATIVE = re.compile(r"^-\.?\d")


class Parser(argparse.ArgumentParser):
    """``flowrt`` and every subcommand (``add_subparsers`` makes its parsers of this class)."""

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        given = list(sys.argv[1:] if args is None else args)
        self._given = given
        ns, extras = super().parse_known_args(self._joined(given), namespace)
        if extras:  # refused where they were given: a subcommand's before they reach flowrt
            self.unrecognized(extras)
        return ns, extras

    def unrecognized(self, extras: list[str]) -> NoReturn:
        hints = []
        for word in extras:
            if word.startswith("-") and not _NEGATIVE.match(word):
                match = closest(word.split("=", 1)[0], self._long_options())
                if match is not None:
                    hints.append(f"did you mean {match}?")
        self.error(
            f"unrecognized arguments: {' '.join(extras)}" + "".join(f" ({h})" for h in hints)
        )

    def _hint(self, message: str) -> str:
        """A suggestion for argparse's own errors: a misspelt subcommand (``invalid choice:
        'rnu'``), or an unknown option that left a required argument missing."""
        choice = re.match(r"argument (\S+): invalid choice: '([^']*)'", message)
        if choice is not None:
            # the named argument's choices only (all of them offered 'flowrt' for a
            # --writer-priority of 'low')
            named = choice.group(1).split("/")
            names = [
                str(n)
                for a in self._actions
                if a.choices
                and (set(a.option_strings) & set(named) or a.metavar in named or a.dest in named)
                for n in a.choices
            ]
            match = closest(choice.group(2), names)
            return f" (did you mean {match}?)" if match is not None else ""
        if message.startswith("the following arguments are required"):
            for word in getattr(self, "_given", []):
                if word.startswith("--") and self._option_for(word) is None:
                    match = closest(word.split("=", 1)[0], self._long_options())
                    if match is not None:
                        return f" ({word}: did you mean {match}?)"
        return ""

    def _long_options(self) -> list[str]:
        return [o for o in self._option_string_actions if o.startswith("--") and o != "--help"]

    def _joined(self, args: list[str]) -> list[str]:
        """``--opt -3s`` as ``--opt=-3s``: a value that looks negative is still a value."""
        out: list[str] = []
        i = 0
        while i < len(args):
            word = args[i]
            action = self._option_for(word)
            if (
                action is not None
                and action.nargs in (None, "?")
                and i + 1 < len(args)
                and _NEGATIVE.match(args[i + 1])
            ):
                out.append(f"{word}={args[i + 1]}")
                i += 2
                continue
            if word == "--":
                out.extend(args[i:])
                break
            out.append(word)
            i += 1
        return out

    def _option_for(self, word: str) -> argparse.Action | None:
        if not word.startswith("-") or "=" in word:
            return None
        action = self._option_string_actions.get(word)
        if action is None and word.startswith("--") and self.allow_abbrev:
            found = [o for o in self._option_string_actions if o.startswith(word)]
            if len({id(self._option_string_actions[o]) for o in found}) == 1:
                action = self._option_string_actions[found[0]]
        return action

    def _missing_command(self, message: str) -> list[str] | None:
        """The choices of this parser's subcommand when the message says it is missing (``the
        following arguments are required: ctl_command``: argparse names it by its dest)."""
        prefix = "the following arguments are required: "
        if not message.startswith(prefix):
            return None
        names = message.removeprefix(prefix).split(", ")
        for action in self._actions:
            if isinstance(action, argparse._SubParsersAction) and (
                action.dest in names or action.metavar in names
            ):
                return list(action.choices or ())
        return None

    def _sub_options(self) -> set[str]:
        """Every option of this parser's subcommands, nested ones included."""
        out: set[str] = set()
        for action in self._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub in action.choices.values():
                    out.update(sub._option_string_actions)
                    if isinstance(sub, Parser):
                        out |= sub._sub_options()
        return out

    def error(self, message: str) -> NoReturn:
        commands = self._missing_command(message)
        if commands is not None:
            # One line in the user's words: ``ctl_command`` is argparse's name for it, and an
            # option of a subcommand given before one (``flowrt ctl --json``) is no typo.
            sub = self._sub_options()
            given = getattr(self, "_given", [])
            self._given = [w for w in given if w.split("=", 1)[0] not in sub]
            hint = self._hint(message)
            self.exit(
                2,
                f"{self.prog}: say what to do: {', '.join(commands)} ({self.prog} --help){hint}\n",
            )
        message += self._hint(message)
        for action in self._actions:  # ``argument ctl_command: invalid choice``: not its name
            if isinstance(action, argparse._SubParsersAction) and action.dest:
                message = message.replace(f"argument {action.dest}: ", "", 1)
        self.print_usage(sys.stderr)
        self.exit(2, f"{self.prog}: error: {message}\n")
