"""The model: what is simulated, as values and shapes (the scenario, the channel's mesh, the boundary data, where
cells start, the IDT drive's lag, the arrivals). Imports nothing of the method or the machinery."""
