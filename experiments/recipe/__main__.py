import sys

from experiments.recipe.cli import main

sys.exit(main())
