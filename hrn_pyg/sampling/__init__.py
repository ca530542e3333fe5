"""Monte Carlo graph-convolutional dropout: K futures in one batched graph, and their scores."""

from hrn_pyg.sampling.sample import make_masks_fn, sample

__all__ = ["make_masks_fn", "sample"]
