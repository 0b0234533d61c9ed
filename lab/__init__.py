"""The lab application, its layers top to bottom (docs/architecture.md):

    lab.cli       the `lab` command (imports the layers below only inside its commands)
    lab.studies   the `lab bench ...` studies
    procedures    BORG, truss, calibration, survey (top-level package)
    drivers | estimation | sim_devices   side by side, independent (top-level packages)
    lab.core      the kernel every layer stands on

`lab/rigs/` holds the rig files shipped with the package (data, no code)."""
