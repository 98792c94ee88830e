"""Node clocks: NTP samples, the offset and drift model, corrections and their bounds, the UDP exchange."""
