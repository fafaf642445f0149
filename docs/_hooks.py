"""mkdocs hooks: serve the figures under ``results/`` that the pages show.

The pages link them as ``../results/<problem>/<figure>.png`` (the path that also works on a code
host); the site holds them at ``results/<problem>/<figure>.png``.
"""

import os

from mkdocs.structure.files import File


def on_files(files, config):
    root = os.path.dirname(config["config_file_path"])
    for problem in sorted(os.listdir(os.path.join(root, "results"))):
        folder = os.path.join(root, "results", problem)
        if not os.path.isdir(folder):
            continue
        for name in sorted(os.listdir(folder)):
            if name.endswith(".png"):
                files.append(File(f"results/{problem}/{name}", root, config["site_dir"],
                                  config["use_directory_urls"]))
    return files


def on_page_markdown(markdown, page, config, files):
    return markdown.replace("](../results/", "](results/")
