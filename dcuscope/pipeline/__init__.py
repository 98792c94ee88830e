"""dcuscope's pipeline framework: YAML configuration, element checks, source and sink bins, building and running a pipeline, RTSP serving."""
