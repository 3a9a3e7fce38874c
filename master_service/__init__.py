"""The laptop service: TCP server for the robots, evolution rounds with retry, checkpoint and
resume, the run directory, reports, and the ``surprise-master`` command line.

:class:`~master_service.master.Master` runs one experiment (see its module for in-process use);
:class:`~master_service.config.MasterConfig` configures it.
"""

from master_service.config import MasterConfig, load_master_config, load_secret
from master_service.master import Master, Progress, RunSummary

__all__ = ["Master", "MasterConfig", "Progress", "RunSummary", "load_master_config", "load_secret"]
