"""Simulated devices: a seeded world (`world`) and device servers that speak the wire protocols
of docs/protocols.md from the device side (`turntable`, `stewart`, `ipjr`, `camera`), started
together by `bench.start_sim_bench`.  Never imports `drivers` (shared/design.md §1)."""
