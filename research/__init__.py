"""The studies behind lightning_vtr's defaults, kept beside the package: not installed with it, never imported by it.

Run from the repository root, against the installed package (``research/README.md`` lists the studies).
"""
