"""The wire: the gRPC plumbing every role shares (status codes, services, channels, security,
wire<->domain conversion, report streams, health, metrics, logs). It imports the core only."""
