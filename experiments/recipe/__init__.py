"""``python -m experiments.recipe`` (``make checkpoints``): remake the shipped checkpoints from the
recipe in ``data/recipes.toml``. A maintainer's tool, run from the checkout's root (it reads
``data/``), not part of the wheel: :mod:`~experiments.recipe.schema` (the recipe),
:mod:`~experiments.recipe.runner` (generate, train, calibrate, publish; resumable),
:mod:`~experiments.recipe.manifest` (records) and :mod:`~experiments.recipe.cli` (the command line)."""

from experiments.recipe.cli import add_arguments, config_from_args, main, run
from experiments.recipe.manifest import MANIFEST_NAME, RUN_RECORD
from experiments.recipe.runner import Paused, RunConfig, Runner
from experiments.recipe.schema import (
    RECIPE_PATH,
    DatasetRecipe,
    ModelRecipe,
    Recipe,
    load_recipe,
    option_flags,
    parse_recipe,
    shown,
)

#: in the order of the API reference (docs/make_api.py lists ``__all__``)
__all__ = [
    "DatasetRecipe",
    "ModelRecipe",
    "Recipe",
    "option_flags",
    "parse_recipe",
    "load_recipe",
    "RunConfig",
    "Paused",
    "shown",
    "Runner",
    "add_arguments",
    "config_from_args",
    "run",
    "main",
    "MANIFEST_NAME",
    "RECIPE_PATH",
    "RUN_RECORD",
]
