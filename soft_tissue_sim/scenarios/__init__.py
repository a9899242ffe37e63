"""Scripted scenarios: the surgeons that drive a scene's instruments and modifications, for
the benchmarks and the tests."""
