"""``hrn-pyg checkpoints``: remake the shipped checkpoints from the recipe in ``data/recipes.toml``.

:mod:`~hrn_pyg.recipe.schema` reads and validates the recipe, :mod:`~hrn_pyg.recipe.runner`
generates the datasets, trains, calibrates and publishes each model (resuming where a killed
run stopped), :mod:`~hrn_pyg.recipe.manifest` keeps the run records and the checkpoints'
``manifest.json``, and :mod:`~hrn_pyg.recipe.cli` is the sub-command (``add_arguments``,
``run``).
"""

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
