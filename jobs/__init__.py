"""The command-line jobs. Each runs as ``python jobs/NAME.py`` (what ``ray job submit --working-dir .``
runs) or, installed, as ``aniformer-NAME`` (``[project.scripts]`` in pyproject.toml)."""
