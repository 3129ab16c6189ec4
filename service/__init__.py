"""The pbrsr job service: a FastAPI app (``service.app:create_app``) with the upload API,
job status, bundles, the dashboard and metrics. A thin layer over ``pbrsr_core``."""
