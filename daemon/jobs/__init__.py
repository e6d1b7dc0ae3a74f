"""What the controller runs on the rig, one at a time: the job's common life (job.py), the scan
and its steps (depth sweep, capture, retake), the calibration rotation and the focus sweep, the
phones' preparation and the verified pulls of their pictures, and the controller that starts
jobs, aborts them and resets a latched fault.
"""
