"""The HTTP API, stored sessions' routes and the browsers' Socket.IO namespace."""
