"""The sorting controller and the fluorescence-detector stub (plain data in, decisions out)."""
