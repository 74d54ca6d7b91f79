"""fwdstep.sweeps"""
