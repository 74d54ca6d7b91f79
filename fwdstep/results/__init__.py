"""fwdstep.results"""
