"""needletissue.studies"""
