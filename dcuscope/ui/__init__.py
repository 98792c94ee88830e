"""The dcuscope web page (``ui/static/``), served by the relay at ``/``; ``ui.vendor`` installs its
front-end packages into ``ui/static/vendor/``."""
