"""Helpers for tests and benchmarks that do not ship in the package: random valid messages
(:mod:`tests.support.samples`) and fuzzed payloads (:mod:`tests.support.fuzz`)."""
