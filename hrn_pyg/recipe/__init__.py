"""``hrn-pyg checkpoints``: remake the shipped checkpoints from the recipe in ``data/recipes.toml``:
:mod:`~hrn_pyg.recipe.schema` (the recipe), :mod:`~hrn_pyg.recipe.runner` (generate, train,
calibrate, publish; resumable), :mod:`~hrn_pyg.recipe.manifest` (records) and
:mod:`~hrn_pyg.recipe.cli` (the sub-command)."""

from hrn_pyg.recipe.cli import add_arguments, config_from_args, run
from hrn_pyg.recipe.manifest import MANIFEST_NAME, RUN_RECORD
from hrn_pyg.recipe.runner import Paused, RunConfig, Runner
from hrn_pyg.recipe.schema import (
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
    "MANIFEST_NAME",
    "RECIPE_PATH",
    "RUN_RECORD",
]
