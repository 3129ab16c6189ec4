"""The job system that the service and the workers share: the job store in Redis and on
disk (``store``: layout, index, states, events, the options a job may carry) and the
deployment's settings (``settings``: environment variables ``PBRSR_*``). It builds on
``pbrsr_core`` for the method's options and limits; ``pbrsr_core`` never imports it."""
