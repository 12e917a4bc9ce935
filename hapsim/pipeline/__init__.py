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
    The run of a 2-D or 3-D scene.
:mod:`hapsim.pipeline.identify_run`
    ``hapsim identify``'s run: the device's mass, friction and delay from a record.
:mod:`hapsim.pipeline.haply2_host`, :mod:`hapsim.pipeline.falcon_run`
    The runs of the Haply 2DIY and the Novint Falcon.
:mod:`hapsim.pipeline.contact_replay`
    Which samples had every contact engaged, replayed from the telemetry.
"""
