"""The robustness-map tests' dataset fixtures (shared with the score-validity study's tests)."""

from robustness_fixtures import dataset_root, objects  # noqa: F401 (pytest fixtures)
