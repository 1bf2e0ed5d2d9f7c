"""The service's assembly: what starts every part, in order, binds them to the bus, runs the
background loops and stops them again, with or without a web server in front.

Enters: validated settings, the loaded phantom and robot model and the robot link
(:class:`~service.runtime.context.ServiceInputs`, from :func:`~service.runtime.inputs.prepare_inputs`).
Leaves: the running service (:class:`~service.runtime.context.ServiceContext`, from
:func:`~service.runtime.assembly.running_service`).  The HTTP app's lifespan enters it; it runs
without HTTP too (tests/unit/service/runtime/test_running_service.py).
"""
