"""fwdstep.views"""
