"""What a request brings in, read with bounds before anything large is allocated: a ``.npy`` cube (``upload``), ADC
frames (``adc_upload``) and DCA1000 captures (``capture_upload``), small JSON bodies and headers (``json_body``,
``json_header``), the query's parameters (``query``), and the answer that closes a connection whose body was left
unread (``unread_body``)."""
