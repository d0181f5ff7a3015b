"""Commands and orchestration: the demo (daemons as OS processes), a Zenoh router, certificates
for the secure profile, map export."""
