"""mkdocs hooks: serve the figures under ``results/`` that the pages show.

The pages link them as ``../results/<path>.png`` (the path that also works on a code host); the
site holds them at ``results/<path>.png``, for every ``.png`` under ``results/`` at any depth
(``results/table/<problem>/estimates.png``, say), the run cache apart.

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
    return markdown.replace("](../results/", "](results/")
