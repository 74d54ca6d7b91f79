"""fwdstep.analysis: linearisation and (later) sensitivities of a diagram, from the blocks' one definition."""
