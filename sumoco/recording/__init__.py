"""Recording a run to MCAP (``record``, its compact codec ``codec``) and replaying it onto Zenoh (``replay``)."""
