"""The `lab bench ...` studies: measurements over many runs, above the procedures they run."""
