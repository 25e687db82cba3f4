"""``srl docs``: the documentation pages generated from the code, and the check that they are current.

The reference pages (docs/reference/) are read off the code itself: the settings models and the
packaged srl.toml, the ``srl`` argument parsers, the wire messages and the key expressions.
The benchmark pages (docs/benchmarks/) and the README's headline table are read off the JSON
that ``srl bench ... --json`` printed (kept in docs/benchmarks/data/). Output is deterministic
(sorted, no timestamps of its own), so ``srl docs --check`` can tell a stale page from a current one.
"""
