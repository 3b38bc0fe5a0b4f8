"""Test helpers for filter authors: synthetic streams and the filter contract suite."""

from evchain.testing.contract import ContractError, check_filter, check_source

__all__ = ["ContractError", "check_filter", "check_source"]
