"""What the relay sends elsewhere: Prometheus metrics and OpenTelemetry (OTLP) traces."""
