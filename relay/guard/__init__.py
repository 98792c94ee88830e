"""Guards of the relay: limits, tokens, Host and Origin checks, connection caps, log rate."""
