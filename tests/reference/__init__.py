"""Test oracles: plain numpy twins of occdata's kernels, one module per product module
(`<stage>_<module>.py`), imported by the tests as `reference.<name>`. They are kept out of the product
modules (and their `__all__`) because nothing but the tests calls them."""
