"""fwdstep.run"""
