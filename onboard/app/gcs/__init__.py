"""The ground side: message dispatch, what the app publishes, its parameters on the parameter protocol, long STATUSTEXT."""
