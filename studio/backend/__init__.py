"""Zenoh backend: typed bus protocol, sim and trainer workers, jobs, presence and fault handling."""
