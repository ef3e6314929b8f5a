"""How work runs, apart from what it computes: the task model and the worker side (`tasks`: `Task`,
`TaskFailed`, `worker_setup`), the Dask task runner and stop signals (`cluster`), and the store/output
lock (`lock`). Algorithms never import this package's state; they are handed what they need (a stop
check) by the task that runs them."""
