"""The plant: the SAW cell sorter's channel flow, cells and reduced models (no I/O, no printing)."""
