"""Studies and benchmarks: measurement runs on the simulator and on saved data, which measure
slscan rather than being part of it (the uncertainty coverage, the registration campaign,
view pairs beside Open3D, shiny-part figures, bin poses judged against the truth). Tests and
`slscan bench` use them; `python -m studies.NAME` runs those with a command line of their own.
They may import every package; none of the product's packages imports them."""
