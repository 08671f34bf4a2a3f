"""MkDocs hook: the figures the docs show, copied into the site from where the repository keeps them.

The figures stay beside the results they belong to (experiments/*/); a figure that is missing fails the build (a
FileNotFoundError names it), so a moved result cannot leave a page with a broken image."""

from __future__ import annotations

import pathlib

from mkdocs.structure.files import File

ROOT = pathlib.Path(__file__).resolve().parents[2]
# the site's path -> the repository's file
FIGURES = {
    "figures/obs-returns.png": "experiments/paper_obs_space/figures/returns.png",
    "figures/minatar-profiles.png": "experiments/atari/results/minatar-aggregate/profiles.png",
}


def on_files(files, config):
    for site_path, repo_path in FIGURES.items():
        source = ROOT / repo_path
        if not source.is_file():
            raise FileNotFoundError(f"docs/hooks/repo_files.py: {repo_path} is not in the repository; update FIGURES")
        files.append(File.generated(config, site_path, abs_src_path=str(source)))
    return files
