package com.tbp.agent;

import java.io.Closeable;
import java.io.IOException;
import java.io.InputStream;
import java.io.OutputStream;
import java.util.ArrayDeque;

/**
 * A client over a socket's streams (a LocalSocket on the phone): a reader thread hands its bytes
 * to the agent, a writer thread sends the queued answers, so a client that stops reading never
 * blocks the dispatcher. More than {@value #MAX_QUEUED_BYTES} bytes of unsent answers close the
 * connection: that client is gone or broken.
 */
public final class StreamConnection implements Connection {

    public static final int MAX_QUEUED_BYTES = 1 << 20;

    private final String name;
    private final InputStream in;
    private final OutputStream out;
    private final Closeable socket;
    private final Agent agent;
    private final Log log;
    private final ArrayDeque<byte[]> queue = new ArrayDeque<>();
    private int queuedBytes;
    private boolean closed;

    public StreamConnection(String name, InputStream in, OutputStream out, Closeable socket, Agent agent, Log log) {
        this.name = name;
        this.in = in;
        this.out = out;
        this.socket = socket;
        this.agent = agent;
        this.log = log;
    }

    /** Announces the connection to the agent and starts its reader and writer threads. */
    public void start() {
        agent.opened(this);
        Thread reader = new Thread(new Runnable() {
            @Override
            public void run() {
                read();
            }
        }, name + "-read");
        Thread writer = new Thread(new Runnable() {
            @Override
            public void run() {
                write();
            }
        }, name + "-write");
        reader.setDaemon(true);
        writer.setDaemon(true);
        reader.start();
        writer.start();
    }

    private void read() {
        byte[] buffer = new byte[16 * 1024];
        try {
            int n;
            while ((n = in.read(buffer)) >= 0) {
                if (n > 0) {
                    agent.received(this, buffer, 0, n);
                }
            }
        } catch (IOException e) {
            if (!isClosed()) {
                log.info(name + ": read failed: " + e.getMessage());
            }
        }
        agent.closed(this);
    }

    private void write() {
        try {
            while (true) {
                byte[] line;
                synchronized (this) {
                    while (queue.isEmpty() && !closed) {
                        wait();
                    }
                    if (closed) {
                        return;
                    }
                    line = queue.poll();
                    queuedBytes -= line.length;
                }
                out.write(line);
                out.flush();
            }
        } catch (IOException e) {
            if (!isClosed()) {
                log.info(name + ": write failed: " + e.getMessage());
            }
            agent.closed(this);
        } catch (InterruptedException e) {
            Thread.currentThread().interrupt();
        }
    }

    private synchronized boolean isClosed() {
        return closed;
    }

    @Override
    public void send(byte[] line) {
        boolean overflow;
        synchronized (this) {
            if (closed) {
                return;
            }
            overflow = queuedBytes + line.length > MAX_QUEUED_BYTES;
            if (!overflow) {
                queue.add(line);
                queuedBytes += line.length;
                notifyAll();
            }
        }
        if (overflow) {
            log.info(name + ": more than " + MAX_QUEUED_BYTES + " bytes of answers unread, closing");
            agent.closed(this);
        }
    }

    @Override
    public void close() {
        synchronized (this) {
            if (closed) {
                return;
            }
            closed = true;
            queue.clear();
            notifyAll();
        }
        try {
            socket.close();
        } catch (IOException e) {
            log.info(name + ": close failed: " + e.getMessage());
        }
    }
}
