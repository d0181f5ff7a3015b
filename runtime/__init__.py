"""The common runtime every process shares: typed TOML config, Zenoh sessions, logging, errors
and exit codes, bounded queues, allocator tuning for hot loops."""
