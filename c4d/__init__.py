"""c4d: the shell around the three packages (command line, configs, errors, inspection, demo).

`c4d.config`, `c4d.errors` and `c4d.system` are leaf modules that `datagen`, `dynpt` and
`c4d_pipeline` may import; `c4d.cli`, `c4d.inspect` and `c4d.demo` sit on top of all three.
"""

__version__ = "0.1.0"
