"""Run the tutorial page ``docs/tutorial.md``: its Python blocks, in order, as one script.

    python -m experiments.tutorial [OUT] [--no-extras]    # OUT: default docs/tutorial

Writes the script to ``OUT/tutorial.py``, runs it with ``OUT`` as the working directory (the
trained prior, its run folder and the figure land there) and saves what it printed to
``OUT/output.txt``. ``tests/test_tutorial.py`` runs it in a temporary folder (without the page's
```python extra`` comparison blocks), so the page cannot go stale.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import re
import subprocess
import sys
import time

from experiments import cli, interrupt

PAGE = pathlib.Path(__file__).resolve().parents[1] / "docs" / "tutorial.md"


def code(page: pathlib.Path = PAGE, extras: bool = False) -> str:
    """The page's ```python blocks, joined in order; with ``extras``, also its ```python extra
    blocks (comparisons that the CI test leaves out to save time)."""
    blocks = re.findall(r"^```python( extra)?\n(.*?)^```", page.read_text(), flags=re.S | re.M)
    chosen = [body for extra, body in blocks if extras or not extra]
    if not chosen:
        raise ValueError(f"{page} has no ```python blocks")
    return "\n\n".join(chosen)


def run(out: str, page: pathlib.Path = PAGE, extras: bool = False) -> str:
    """Run the tutorial in ``out`` (``extras``: with its extra blocks); returns its stdout.
    Raises CalledProcessError on failure."""
    out_dir = pathlib.Path(out).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    script = out_dir / "tutorial.py"
    script.write_text(code(page, extras))
    env = {**os.environ, "MPLBACKEND": "Agg"}
    t0 = time.perf_counter()
    done = interrupt.run([sys.executable, str(script)], cwd=out_dir, env=env, text=True,
                         capture_output=True)
    seconds = time.perf_counter() - t0
    if done.returncode != 0:
        raise subprocess.CalledProcessError(done.returncode, done.args, done.stdout,
                                            done.stderr[-4000:])
    (out_dir / "output.txt").write_text(done.stdout + f"[{seconds:.0f} s]\n")
    return done.stdout


DESCRIPTION = ("Run the Python blocks of docs/tutorial.md as one script in OUT: write "
               "OUT/tutorial.py, run it there (its trained prior, run folder and figure land in "
               "OUT) and save what it printed to OUT/output.txt.")


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m experiments.tutorial``."""
    p = argparse.ArgumentParser(prog="python -m experiments.tutorial", description=DESCRIPTION)
    p.add_argument("out", nargs="?", default=str(PAGE.parent / "tutorial"), metavar="OUT",
                   help="folder to run the tutorial in (default %(default)s)")
    p.add_argument("--no-extras", action="store_true",
                   help="leave out the page's ```python extra comparison blocks, as the CI test "
                        "does")
    return p


def parse_args(argv=None) -> argparse.Namespace:
    p = build_parser()
    args = p.parse_args(argv)
    cli.check_folder(p, "OUT", args.out)
    return args


def main(argv=None):
    args = parse_args(argv)
    t0 = time.perf_counter()
    print(run(args.out, extras=not args.no_extras), end="")
    print(f"tutorial ran in {time.perf_counter() - t0:.0f} s; outputs in {args.out}")


if __name__ == "__main__":
    interrupt.main(main, "tutorial")
