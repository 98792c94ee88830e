"""Guards of the relay: the access policy and sign-in, token files, limits, Host and Origin checks,
connection caps, log rate."""
