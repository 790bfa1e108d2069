"""The pieces of `tpdeb-cluster` (services/cluster.py): the plan, restart policies, supervised
children and the status display."""

PROG = "tpdeb-cluster"
