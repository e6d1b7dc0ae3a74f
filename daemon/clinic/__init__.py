"""The clinic's side of a scan: who it is of (patient and study), the site file, the worklist.

The scan folder's manifest carries the patient and the study (daemon/records/manifest.py); nothing here
writes a patient's identity anywhere else, least of all into a log line.
"""
