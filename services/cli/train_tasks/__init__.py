"""One module per trainable task: `register(task_subparsers)` adds `n3dmap train <task>`.

Build the parser with `services.cli.train.add_task_parser` (the shared options) and run it with
`services.cli.train.run_train(task, args, task_options)`; see services/cli/train.py.
"""
