"""TPDEB's processes: the thin shells (config, clocks, files, signals, transport) around
`tpdeb_core`."""
