"""The plant as an FMI 2.0 co-simulation FMU (pythonfmu), and FMUs as plants (fmpy).

``msagv fmu build`` -> :mod:`fmu_build.build`; the slave inside the FMU is
:mod:`fmu_build.slave`; :class:`fmu_build.host.FmuPlant` hosts any FMU behind
``plant.Plant``'s interface. See ``docs/FMU.md``. Nothing is imported here, so
``msagv fmu`` pays only for what it runs.
"""
