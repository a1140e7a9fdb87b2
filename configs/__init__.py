"""The shipped presets, one folder per config group; installed as the package `c4d_configs`."""
