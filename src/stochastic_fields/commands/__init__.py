"""The options of the commands that ``stochastic_fields.cli`` loads on demand (one module each).

Each module holds ``add_arguments(parser)`` and ``run(args)``; ``run`` imports the implementation
only when the command runs, so ``stochastic-fields COMMAND --help`` never loads torch.
"""
