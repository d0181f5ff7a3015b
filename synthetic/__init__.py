"""Synthetic traffic without SUMO (``traffic``: random steps, circle traffic, a junction grid)
and its Zenoh feed (``feed``), for benchmarks, tests and the viewer's demo feed. Below the sides:
nothing of the product daemons imports it."""
