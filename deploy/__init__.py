"""What operators deploy beside the agent. deploy/mixin is a Python package: its build renders the
monitoring mixin (`python -m deploy.mixin.build`)."""
