"""fwdstep.compiled"""
