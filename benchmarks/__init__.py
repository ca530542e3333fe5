"""One script per question, each printing a table and writing JSON: ``python -m benchmarks.<name>``
from the checkout (docs/performance.md). What several share is in :mod:`benchmarks.common`."""
