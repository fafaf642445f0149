"""Checks of the jobs' command lines that run before any work, so that a bad value ends in
argparse's one-line error naming the flag (exit status 2), not in a traceback after the
computation: numbers (``positive_float``), the folders a job writes (``--out``, ``--cache``,
``OUT``) and the pages whose generated block it rewrites (``--page``, ``--readme``), and the
values ``--quick`` gives to the flags the command line left out (``fill``).
"""

from __future__ import annotations

import argparse
import math
import os
import pathlib


def positive_float(text: str) -> float:
    """An argparse ``type``: a finite float ``> 0`` (``nan``, ``inf``, 0 and below are refused)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text!r}")
    return value


positive_float.__name__ = "float > 0"


def folder_problem(path: str) -> str | None:
    """Why a job cannot write into the folder ``path`` (created with its parents if missing),
    or None: it is a file, lies under a file, or the folder or its nearest existing parent is
    not writable."""
    target = pathlib.Path(path).absolute()
    if target.exists():
        if not target.is_dir():
            return f"{path} is a file, not a folder; give a folder (it is created if missing)"
        if not os.access(target, os.W_OK | os.X_OK):
            return f"the folder {path} is not writable; give a folder you can write to"
        return None
    parent = next(p for p in target.parents if p.exists())
    if not parent.is_dir():
        return (f"{path} lies under {parent}, which is a file, not a folder; give a folder "
                f"(it is created if missing)")
    if not os.access(parent, os.W_OK | os.X_OK):
        return f"cannot create {path}: {parent} is not writable; give a folder you can write to"
    return None


def markers(tag: str | None = None) -> tuple:
    """The start and end markers of a page's generated block (``harness.publish``)."""
    name = "results" if tag is None else f"results:{tag}"
    return f"<!-- {name}:start -->", f"<!-- {name}:end -->"


def page_problem(path: str, tag: str | None = None) -> str | None:
    """Why a job cannot rewrite the generated block ``tag`` of the page ``path``, or None: it is
    missing, a folder, not readable and writable, or lacks the block's markers."""
    target = pathlib.Path(path)
    if not target.exists():
        return f"{path} does not exist; give an existing page with the block's markers"
    if not target.is_file():
        return f"{path} is a folder, not a page; give a page with the block's markers"
    if not os.access(target, os.R_OK | os.W_OK):
        return f"the page {path} is not writable; give a page you can write to"
    start, end = markers(tag)
    try:
        text = target.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        return f"cannot read the page {path} ({type(e).__name__}); give a text page"
    if start not in text or end not in text:
        return f"{path} lacks the {start} / {end} markers; add them where the block goes"
    return None


def check_folder(p: argparse.ArgumentParser, flag: str, path: str | None) -> None:
    """``p.error`` naming ``flag`` if the folder ``path`` cannot be written (None: not given)."""
    problem = None if path is None else folder_problem(path)
    if problem:
        p.error(f"argument {flag}: {problem}")


def check_page(p: argparse.ArgumentParser, flag: str, path: str | None,
               tag: str | None = None) -> None:
    """``p.error`` naming ``flag`` if the block ``tag`` of the page ``path`` cannot be
    rewritten (None: not given)."""
    problem = None if path is None else page_problem(path, tag)
    if problem:
        p.error(f"argument {flag}: {problem}")


def check_outputs(p: argparse.ArgumentParser, args, tag: str | None = None) -> None:
    """The flags of ``harness.parser`` and ``harness.add_outputs`` that the job has: ``--out``
    and ``--cache`` folders, and the block ``tag`` of the ``--page``."""
    check_folder(p, "--out", getattr(args, "out", None))
    check_folder(p, "--cache", getattr(args, "cache", None))
    check_page(p, "--page", getattr(args, "page", None), tag)


def fill(args, defaults: dict, quick: dict | None = None):
    """Set each attribute of ``args`` named in ``defaults`` that the command line left None
    (flags whose argparse default is None): to its ``quick`` value if given, else its default.
    So a flag given explicitly wins over ``--quick``. Returns ``args``."""
    for name, default in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, (quick or {}).get(name, default))
    return args
