"""slab"""
