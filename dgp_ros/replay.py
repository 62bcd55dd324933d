"""The offline replay's documented import path; the code lives in ``dgp_ros/apps/replay.py``."""
from dgp_ros.apps.replay import (arrays_of, build_config, CsvWriter, load_params_file, main,
                                 make_plots, replay, ReplayError, run, summarize, write_csv,
                                 write_summary)

__all__ = ['build_config', 'load_params_file', 'main', 'replay', 'ReplayError', 'run',
           'arrays_of', 'CsvWriter', 'make_plots', 'summarize', 'write_csv', 'write_summary']
