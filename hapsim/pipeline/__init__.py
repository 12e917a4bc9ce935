"""One run's pipeline: calibrate, check, close the THS, identify, report.

Modules
-------
:mod:`hapsim.pipeline.runner`
    ``run_scene``: the steps of one run (the prediction and the measurement are
    :mod:`hapsim.analysis.prediction` and :mod:`hapsim.analysis.measurement`); its steps'
    results are the records of :mod:`hapsim.pipeline.run_types`, its identification step
    :mod:`hapsim.pipeline.measure`, its options :mod:`hapsim.pipeline.options`, its report
    :mod:`hapsim.pipeline.report`, its start-up :mod:`hapsim.pipeline.startup`.
:mod:`hapsim.pipeline.felt_port`
    The run of a 2-D or 3-D scene (its session over the port, HELLO, quiet between
    records and the port opened again after a loss: :mod:`hapsim.pipeline.port_session`).
:mod:`hapsim.pipeline.identify_run`, :mod:`hapsim.pipeline.excitation`
    ``hapsim identify``'s run: the device's mass, friction and delay from a record, and
    the excitation it designs from what the device shows.
:mod:`hapsim.pipeline.haply2_host`, :mod:`hapsim.pipeline.falcon_run`
    The runs of the Haply 2DIY and the Novint Falcon (the 2DIY's real-time record loop
    :mod:`hapsim.pipeline.haply2_record`, its emulated board's child process
    :mod:`hapsim.pipeline.haply2_embedded`).
:mod:`hapsim.pipeline.contact_replay`
    Which samples had every contact engaged, replayed from the telemetry.
"""
