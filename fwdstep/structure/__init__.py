"""fwdstep.structure"""
