"""`slscan bench NAME`: the benchmarks and studies, one module per bench (the table of them is
`slscan.commands.BENCHES`). Measurement runs, not everyday use: they time slscan, or measure
it against the simulator's truth, and only they may import `studies` (so the module of the
user's `slscan coverage`, which runs the repeat-scan study, is here too)."""
