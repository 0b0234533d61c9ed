"""Rig files shipped with `lab` (package data): `sim.toml`, the default simulated bench, and
`hardware_example.toml`, a template for a real one.  See README.md here and docs/hardware.md."""
