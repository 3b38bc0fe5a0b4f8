"""The framework: packets, the filter contract, the registry, pipelines and the chain."""
