"""mkdocs hooks: serve the figures under ``results/`` that the pages show, and point the
changelog's links at the site's pages.

The pages link the figures as ``../results/<path>.png`` (the path that also works on a code host);
the site holds them at ``results/<path>.png``, for every ``.png`` under ``results/`` at any depth
(``results/table/<problem>/estimates.png``, say), the run cache apart.

``docs/changelog.md`` is ``CHANGELOG.md`` of the repository's root (its one line includes it),
whose links read ``docs/<page>.md``, the path from the root: this hook puts the file in its place
with those links as the site's ``<page>.md``.

mkdocs imports this file from ``docs/``, so Python may leave ``docs/__pycache__/`` behind;
``exclude_docs`` in mkdocs.yml keeps it (and this file) out of the site.
"""

import os

from mkdocs.structure.files import File

SKIP = {"cache"}


def on_files(files, config):
    root = os.path.dirname(config["config_file_path"])
    results = os.path.join(root, "results")
    if not os.path.isdir(results):
        return files
    for folder, dirs, names in os.walk(results):
        dirs[:] = sorted(d for d in dirs if d not in SKIP)
        for name in sorted(names):
            if name.endswith(".png"):
                path = os.path.relpath(os.path.join(folder, name), root).replace(os.sep, "/")
                files.append(File(path, root, config["site_dir"], config["use_directory_urls"]))
    return files


def on_page_markdown(markdown, page, config, files):
    if page.file.src_uri == "changelog.md":
        root = os.path.dirname(config["config_file_path"])
        with open(os.path.join(root, "CHANGELOG.md"), encoding="utf-8") as f:
            markdown = f.read().replace("](docs/", "](")
    return markdown.replace("](../results/", "](results/")
