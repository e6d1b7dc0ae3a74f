package com.tbp.agent;

import static org.junit.Assert.assertEquals;
import static org.junit.Assert.assertTrue;

import java.io.BufferedReader;
import java.io.IOException;
import java.io.InputStreamReader;
import java.io.OutputStream;
import java.net.InetAddress;
import java.net.ServerSocket;
import java.net.Socket;
import java.nio.charset.StandardCharsets;
import java.util.Arrays;
import java.util.Map;
import java.util.concurrent.CountDownLatch;
import org.junit.Test;

/** A client over real sockets, as a LocalSocket is on the phone: its reader and writer threads. */
public class StreamConnectionTest {

    @Test
    public void answersOverASocketAndNoticesTheClientLeaving() throws Exception {
        final Agent agent = new Agent(new Fakes.Camera(), new ImageStore(Fakes.folder(), new Fakes.Disk()),
                new Fakes.Recorder());
        Thread dispatcher = new Thread(new Runnable() {
            @Override
            public void run() {
                try {
                    agent.run();
                } catch (InterruptedException e) {
                    Thread.currentThread().interrupt();
                }
            }
        });
        dispatcher.start();
        try (ServerSocket server = new ServerSocket(0, 1, InetAddress.getLoopbackAddress());
             Socket client = new Socket(InetAddress.getLoopbackAddress(), server.getLocalPort())) {
            Socket accepted = server.accept();
            StreamConnection connection = new StreamConnection("test", accepted.getInputStream(),
                    accepted.getOutputStream(), accepted, agent, new Fakes.Recorder());
            connection.start();
            OutputStream out = client.getOutputStream();
            BufferedReader in = new BufferedReader(new InputStreamReader(client.getInputStream(), StandardCharsets.UTF_8));
            out.write("{\"id\": 1, \"op\": \"clo".getBytes(StandardCharsets.UTF_8));
            out.flush();
            out.write("ck\"}\n{\"id\": 2, \"op\": \"hello\"}\n".getBytes(StandardCharsets.UTF_8));
            out.flush();
            Map<?, ?> first = (Map<?, ?>) Json.parse(in.readLine());
            Map<?, ?> second = (Map<?, ?>) Json.parse(in.readLine());
            // answers in any order: the clock's comes back through the camera, hello's at once
            assertEquals(3L, (Long) first.get("id") + (Long) second.get("id"));
            client.shutdownOutput();  // the host closes its stream: the agent closes its side
            assertEquals(null, in.readLine());
        } finally {
            agent.stop();
            dispatcher.join(10_000);
        }
    }

    @Test(timeout = 60_000)  // a send that blocked would hang here
    public void aClientThatStopsReadingIsClosedNotWaitedFor() throws Exception {
        Agent agent = new Agent(new Fakes.Camera(), new ImageStore(Fakes.folder(), new Fakes.Disk()),
                new Fakes.Recorder());
        final CountDownLatch never = new CountDownLatch(1);
        OutputStream stuck = new OutputStream() {
            @Override
            public void write(int b) throws IOException {
                try {
                    never.await();
                } catch (InterruptedException e) {
                    throw new IOException(e);
                }
            }
        };
        final boolean[] socketClosed = {false};
        StreamConnection connection = new StreamConnection("stuck", new java.io.ByteArrayInputStream(new byte[0]) {
            @Override
            public synchronized int read(byte[] b, int off, int len) {
                try {
                    never.await();
                } catch (InterruptedException e) {
                    return -1;
                }
                return -1;
            }
        }, stuck, new java.io.Closeable() {
            @Override
            public void close() {
                socketClosed[0] = true;
            }
        }, agent, new Fakes.Recorder());
        connection.start();
        byte[] line = new byte[1000];
        Arrays.fill(line, (byte) ' ');
        for (int i = 0; i < 2 * StreamConnection.MAX_QUEUED_BYTES / line.length; i++) {
            connection.send(line);  // never blocks, however little the client reads
        }
        agent.runPending();
        assertTrue(socketClosed[0]);
        never.countDown();
    }
}
