"""How work runs, apart from what it computes: the Dask task runner (`cluster`), stop signals, and the
store/output lock (`lock`). Algorithms never import this package's state; they are handed what they
need (a stop check) by the command that runs them."""
