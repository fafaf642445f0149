"""The experiments' command lines: one parser factory and the argument types they share. A bad value
is argparse's one-line ``error: argument --runs: ...`` (exit status 2), never a silent default or a
deep traceback, and it is caught before any expensive work starts."""

from __future__ import annotations

import argparse


def parser(module: str, description: str, **kwargs) -> argparse.ArgumentParser:
    """The parser of ``python -m experiments.<module>``: ``description`` is one line saying what
    the job does and what it writes; the epilog points at the module docstring for the details.
    Every argument is expected to carry a ``help`` string, with ``%(default)s`` for its default."""
    kwargs.setdefault("epilog", f"Details: the docstring of experiments/{module}.py.")
    return argparse.ArgumentParser(prog=f"python -m experiments.{module}",
                                   description=description, **kwargs)


def int_at_least(low: int, high: int | None = None, why: str = ""):
    """An argparse ``type``: an int ``>= low`` (and ``<= high`` when given); ``why``, when given,
    says why the bounds are there."""
    reason = f" ({why})" if why else ""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"must be >= {low}, got {value}{reason}")
        if high is not None and value > high:
            raise argparse.ArgumentTypeError(f"must be <= {high}, got {value}{reason}")
        return value

    parse.__name__ = f"int >= {low}" if high is None else f"int in [{low}, {high}]"
    return parse


positive_int = int_at_least(1)
nonnegative_int = int_at_least(0)
particle_count = int_at_least(2)


def multiple_of(step: int, why: str = ""):
    """An argparse ``type``: a positive multiple of ``step`` (``why`` says why)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < 1 or value % step:
            raise argparse.ArgumentTypeError(f"must be a positive multiple of {step}, got {value}"
                                             + (f" ({why})" if why else ""))
        return value

    parse.__name__ = f"multiple of {step}"
    return parse


def one_of(known, what: str):
    """An argparse ``type``: one name from ``known`` (``choices=`` for a ``nargs="*"`` positional,
    which argparse would check as a whole list when it is left empty)."""

    def parse(text: str) -> str:
        if text not in known:
            raise argparse.ArgumentTypeError(f"unknown {what} {text!r}; choose from "
                                             f"{', '.join(known)}")
        return text

    parse.__name__ = what
    return parse


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
