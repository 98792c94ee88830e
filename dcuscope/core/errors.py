"""The errors every package builds on: :class:`DcuscopeError`, the base of every error a user can
cause, and those of configurations, command lines and pipelines. Each names the file, key,
option or element at fault."""


class DcuscopeError(Exception):
    """Base of every error a user can cause; the CLI prints it on one line and exits 2."""


class ConfigError(DcuscopeError):
    """The YAML configuration is malformed or names something that does not exist."""


class UsageError(DcuscopeError):
    """A command-line argument that cannot be used: an output path, a taken port."""


class PipelineError(DcuscopeError):
    """The GStreamer pipeline could not be built or stopped with an error."""
