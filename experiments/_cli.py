"""Argument types shared by the experiments' command lines: a bad value is argparse's one-line
``error: argument --runs: ...`` (exit status 2), never a silent default or a deep traceback."""

from __future__ import annotations

import argparse


def int_at_least(low: int):
    """An argparse ``type``: an int ``>= low``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"must be >= {low}, got {value}")
        return value

    parse.__name__ = f"int >= {low}"
    return parse


positive_int = int_at_least(1)
nonnegative_int = int_at_least(0)
particle_count = int_at_least(2)


def int_list(low: int):
    """An argparse ``type``: a comma-separated, non-empty list of ints ``>= low``."""
    item = int_at_least(low)

    def parse(text: str) -> tuple[int, ...]:
        values = tuple(item(v.strip()) for v in text.split(",") if v.strip())
        if not values:
            raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}")
        return values

    parse.__name__ = f"list of int >= {low}"
    return parse


def name_list(known, what: str):
    """An argparse ``type``: a comma-separated, non-empty list of names from ``known``, no repeats."""

    def parse(text: str) -> list[str]:
        names = [n.strip() for n in text.split(",") if n.strip()]
        unknown = [n for n in names if n not in known]
        if unknown or not names:
            shown = ", ".join(map(repr, unknown)) if unknown else repr(text)
            raise argparse.ArgumentTypeError(f"unknown {what} {shown}; choose from "
                                             f"{', '.join(known)}")
        if len(set(names)) != len(names):
            raise argparse.ArgumentTypeError(f"a {what} is named twice in {text!r}")
        return names

    parse.__name__ = f"{what} list"
    return parse


def write_page(path: str, lines) -> str:
    """Write markdown ``lines`` to ``path`` (one per line), print the page and return its text."""
    text = "\n".join(lines) + "\n"
    with open(path, "w") as f:
        f.write(text)
    print(text)
    return text
