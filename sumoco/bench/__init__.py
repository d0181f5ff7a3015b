"""Every ``sumoco bench ...`` row (``cli`` dispatches); each module measures one part beside its limit."""
