"""fwdstep.core"""
