"""Which network a saved model config builds: the HRN, or the GNS baseline, by its ``network``
field (none: an HRN, as in every checkpoint older than the GNS). Training, loading and
:func:`hrn_pyg.checkpoints.with_applied_options` build models here."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Union

from hrn_pyg.nn import gns
from hrn_pyg.nn.gns import GNS, GNSConfig
from hrn_pyg.nn.hrn import HRN, HRNConfig

#: a network the package's step runs (:mod:`hrn_pyg.sim.step`)
Network = Union[HRN, GNS]
#: a network's config
NetworkConfig = Union[HRNConfig, GNSConfig]
#: the network a config without a ``network`` field builds
DEFAULT_NETWORK = "hrn"
#: ``network`` field -> config class
CONFIGS: dict[str, type] = {DEFAULT_NETWORK: HRNConfig, gns.NETWORK: GNSConfig}


def config_from_dict(d: Mapping[str, Any]) -> NetworkConfig:
    """The config a saved dict describes (its ``network`` field, default ``"hrn"``)."""
    d = dict(d)
    network = d.get("network", DEFAULT_NETWORK)
    if network not in CONFIGS:
        raise ValueError(f"unknown network {network!r}; choose from {sorted(CONFIGS)}")
    if network == DEFAULT_NETWORK:
        d.pop("network", None)
    return CONFIGS[network].from_dict(d)


def build_network(config: NetworkConfig) -> Network:
    """A fresh network of ``config`` (normaliser at the identity)."""
    return GNS(config) if isinstance(config, GNSConfig) else HRN(config)


def network_from_dict(d: Mapping[str, Any]) -> Network:
    """:func:`build_network` of :func:`config_from_dict`."""
    return build_network(config_from_dict(d))


def applied_options(model: Network, hrn_options: tuple[str, ...]) -> tuple[str, ...]:
    """The options that may be changed on ``model``'s trained weights: ``hrn_options`` for an
    HRN, :data:`hrn_pyg.nn.gns.APPLIED_OPTIONS` (the rigid fit) for a GNS."""
    return gns.APPLIED_OPTIONS if isinstance(model, GNS) else hrn_options
